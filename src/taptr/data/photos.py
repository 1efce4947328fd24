"""Real photographs as textures: the built-in licence-clean set, user folders, random crops.

taptr ships no photographs. The built-in set is read at data-generation time from files
that PyPI packages install (the ``photos`` extra); each file is located with
`importlib.util.find_spec`, so the packages are never imported. The set is split once, here,
into photographs for **training** data (`taptr make-synthetic --textures builtin`) and a
disjoint **held-out** set for validation (`taptr make-photo-bench`), so a model is never
scored on a photograph it was trained on:

- train: scikit-learn's ``sklearn/datasets/images/china.jpg`` (CC BY 2.0);
- train: scikit-learn's ``sklearn/datasets/images/flower.jpg`` (CC BY 2.0);
- held-out: matplotlib's ``mpl-data/sample_data/grace_hopper.jpg`` (public domain).

scikit-image's sample images are deliberately not used (they are reserved for evaluation
elsewhere), and neither is any clip of the reference material. docs/LICENSES.md gives the
sources, attributions and licences.

`photo_texture` turns a photograph into a texture of any size: a random crop at a random
scale, flipped or rotated by quarter turns, with a mild colour change, so a handful of
photographs still gives varied layers. Textures only colour a layer; where the layer moves
is decided elsewhere, so ground truth is unaffected.
"""

from __future__ import annotations

import importlib.util
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from taptr.messages import install_line

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".webp", ".tif", ".tiff")
"""File types `load_photo_folder` reads."""


@dataclass(frozen=True)
class PhotoSource:
    """A photograph installed by a PyPI package.

    Attributes:
        name: short name, e.g. ``"china"``.
        package: the importable top-level package that installs the file.
        path: the file's path inside the package folder.
        split: ``"train"`` (synthetic training data) or ``"heldout"`` (the photo benchmark).
        licence: the licence the package states for the file.
        attribution: author and origin, as the package states them.
    """

    name: str
    package: str
    path: str
    split: Literal["train", "heldout"]
    licence: str
    attribution: str


BUILTIN_PHOTOS: tuple[PhotoSource, ...] = (
    PhotoSource(
        "china",
        "sklearn",
        "datasets/images/china.jpg",
        "train",
        "CC BY 2.0",
        "danielbuechele (Flickr), via scikit-learn's load_sample_images",
    ),
    PhotoSource(
        "flower",
        "sklearn",
        "datasets/images/flower.jpg",
        "train",
        "CC BY 2.0",
        "vultilion (Flickr), via scikit-learn's load_sample_images",
    ),
    PhotoSource(
        "grace_hopper",
        "matplotlib",
        "mpl-data/sample_data/grace_hopper.jpg",
        "heldout",
        "public domain (U.S. Navy photograph)",
        "U.S. Navy, via matplotlib's sample data",
    ),
)
"""The built-in photographs; the split is fixed here and documented in the module docstring."""


def builtin_sources(split: Literal["train", "heldout"]) -> tuple[PhotoSource, ...]:
    """The built-in photographs of one split (the two splits share no photograph)."""
    if split not in ("train", "heldout"):
        raise ValueError(f"split must be 'train' or 'heldout', got {split!r}")
    return tuple(source for source in BUILTIN_PHOTOS if source.split == split)


def find_photo(source: PhotoSource) -> Path:
    """The installed file of a built-in photograph, without importing its package.

    Raises:
        ModuleNotFoundError: the package is not installed (the message says what to install).
        FileNotFoundError: the package is installed but no longer ships the file.
    """
    spec = importlib.util.find_spec(source.package)
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError(
            f"the built-in photograph {source.name!r} comes with the {source.package!r} "
            f"package, which is not installed: {install_line('photos')}"
        )
    for folder in spec.submodule_search_locations:
        path = Path(folder) / source.path
        if path.is_file():
            return path
    raise FileNotFoundError(
        f"{source.package} is installed but has no {source.path} (photograph {source.name!r})"
    )


def read_photo(path: str | os.PathLike[str]) -> np.ndarray:
    """Reads an image file as (H, W, 3) uint8 RGB (grey and alpha images are converted).

    Through `taptr.io.image_guard`: the header is checked (format, ``image_pixels``) first.
    """
    from taptr.io.image_guard import STILL_FORMATS, read_image

    return read_image(path, str(path), formats=STILL_FORMATS)


def load_builtin_photos(split: Literal["train", "heldout"]) -> list[np.ndarray]:
    """The built-in photographs of one split, each (H, W, 3) uint8 RGB."""
    return [read_photo(find_photo(source)) for source in builtin_sources(split)]


def load_photo_folder(folder: str | os.PathLike[str], min_size: int = 32) -> list[np.ndarray]:
    """Every image of a folder (not recursive), sorted by file name, as (H, W, 3) uint8 RGB.

    Args:
        folder: a folder of ``.jpg``, ``.png``, ... files (see `PHOTO_SUFFIXES`).
        min_size: images with a side shorter than this are refused (too small to crop).

    Raises:
        FileNotFoundError: the folder does not exist or holds no image.
        ValueError: an image cannot be read or is smaller than ``min_size``.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"no folder of photographs at {folder}")
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES)
    if not paths:
        raise FileNotFoundError(f"no images ({', '.join(PHOTO_SUFFIXES)}) in {folder}")
    photos = []
    for path in paths:
        photo = read_photo(path)
        if min(photo.shape[:2]) < min_size:
            raise ValueError(f"{path} is {photo.shape[1]}×{photo.shape[0]}, below {min_size} px")
        photos.append(photo)
    return photos


def load_textures(spec: str) -> list[np.ndarray]:
    """Photographs named on the command line: ``"builtin"`` (training split) or a folder."""
    if spec == "builtin":
        return load_builtin_photos("train")
    return load_photo_folder(spec)


def photo_texture(
    rng: np.random.Generator,
    photos: Sequence[np.ndarray],
    height: int,
    width: int,
    crop: tuple[float, float] = (0.3, 1.0),
    jitter: float = 0.15,
) -> np.ndarray:
    """A random crop of a random photograph, resized to (height, width).

    Args:
        rng: the only source of randomness.
        photos: photographs, each (h, w, 3) uint8.
        height: texture height in pixels.
        width: texture width in pixels.
        crop: (min, max) side of the crop as a fraction of the largest crop of the target's
            aspect ratio that fits the photograph; small crops zoom in (and blur).
        jitter: largest relative change of each colour channel's gain, and of brightness.

    Returns:
        (height, width, 3) uint8 texture.
    """
    if not photos:
        raise ValueError("no photographs to take a texture from")
    photo = photos[int(rng.integers(len(photos)))]
    # a quarter turn first, so tall and wide crops both come from every photograph
    photo = np.rot90(photo, int(rng.integers(4)))
    rows, cols = photo.shape[:2]
    aspect = width / height
    full_h = min(rows, cols / aspect)  # the largest crop with the target's aspect ratio
    side = full_h * rng.uniform(*crop)
    crop_h, crop_w = max(2, round(side)), max(2, round(side * aspect))
    top = int(rng.integers(0, rows - crop_h + 1))
    left = int(rng.integers(0, cols - crop_w + 1))
    patch = np.ascontiguousarray(photo[top : top + crop_h, left : left + crop_w])
    if rng.random() < 0.5:
        patch = patch[:, ::-1]
    shrink = crop_h > height
    texture = cv2.resize(
        np.ascontiguousarray(patch),
        (width, height),
        interpolation=cv2.INTER_AREA if shrink else cv2.INTER_CUBIC,
    ).astype(np.float32)
    # per-channel gains and a brightness shift: the same photograph seen as different layers
    gains = 1 + rng.uniform(-jitter, jitter, 3) + rng.uniform(-jitter, jitter)
    return (texture * gains.astype(np.float32)).round().clip(0, 255).astype(np.uint8)
