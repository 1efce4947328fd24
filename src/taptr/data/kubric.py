"""Reader (and writer) of the Kubric MOVi-F layout prepared by the CoTracker project.

This is also the documented format for users' own training data. A dataset root holds one
folder per sequence::

    <root>/<seq>/frames/000.png, 001.png, ...   RGB frames, all of the same size
    <root>/<seq>/<seq>.npy                      np.save of a dict:
        coords      float (N, T, 2)  pixel (x, y), pixel centres at integers
        visibility  bool  (N, T)     True where the point is OCCLUDED (despite the name)

The key named ``visibility`` holds occlusion flags: CoTracker's generator stores them under
that name and both CoTracker's and TAPTR's loaders invert it (co-tracker#152). Sequence
folders named by integers (TAPTR's ``r512/{train,val}`` roots) are sorted numerically, and
frames named ``{:03d}.png`` (or any other integer) in numeric order. ``.npy`` files are read
with the restricted unpickler of `taptr.io.safe_pickle`, never with ``allow_pickle``.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from taptr.io import limits
from taptr.io.atomic import atomic_path
from taptr.io.file_kind import kind
from taptr.io.image_guard import image_size, read_image
from taptr.io.safe_npy import load_npy
from taptr.types import TrackingSample

FRAMES_DIR = "frames"
FRAME_SUFFIXES = (".png", ".jpg", ".jpeg")


def _numeric_order(paths: list[Path]) -> list[Path]:
    """Sorts by integer stem when every stem is an integer, else by name."""
    if paths and all(p.stem.isdigit() for p in paths):
        return sorted(paths, key=lambda p: (int(p.stem), p.name))
    return sorted(paths, key=lambda p: p.name)


def list_sequences(root: str | os.PathLike[str]) -> list[Path]:
    """Sequence folders (those with a ``frames/`` folder) under ``root``, in numeric order.

    Raises:
        FileNotFoundError: ``root`` does not exist.
        ValueError: no sequence folder in ``root`` (the message names split folders such as
            ``train``/``val`` when ``root`` is one level too high).
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"dataset root not found: {root}")
    folders = [p for p in root.iterdir() if (p / FRAMES_DIR).is_dir()]
    if folders:
        return _numeric_order(folders)
    splits = sorted(p.name for p in root.iterdir() if p.is_dir() and _has_sequences(p))
    hint = f"; it holds splits {', '.join(splits)}: pass one of them" if splits else ""
    raise ValueError(f"no sequence folders (<seq>/frames/*.png) in {root}{hint}")


def _has_sequences(folder: Path) -> bool:
    """Whether ``folder`` directly holds at least one sequence folder."""
    return any((p / FRAMES_DIR).is_dir() for p in folder.iterdir() if p.is_dir())


def _frame_paths(folder: Path) -> list[Path]:
    frames_dir = folder / FRAMES_DIR
    if not frames_dir.is_dir():
        raise FileNotFoundError(f"{folder}: no {FRAMES_DIR}/ folder")
    paths = [p for p in frames_dir.iterdir() if p.suffix.lower() in FRAME_SUFFIXES]
    if not paths:
        raise ValueError(f"{frames_dir}: no frames ({', '.join(FRAME_SUFFIXES)})")
    return _numeric_order(paths)


def _read_frames(paths: list[Path], bgr: bool) -> np.ndarray:
    height, width = image_size(paths[0], str(paths[0]))
    needed = len(paths) * height * width * 3
    limits.check(
        "video_bytes", needed, f"{paths[0].parent}: {len(paths)} frames of {width}x{height}"
    )
    video = np.empty((len(paths), height, width, 3), np.uint8)
    for index, path in enumerate(paths):
        # header first, decoded by the library that read it (taptr.io.image_guard)
        video[index] = read_image(path, str(path), size=(height, width))
    return video[..., ::-1] if bgr else video


def _read_annotations(path: Path, num_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, T, 2) coordinates and (N, T) occlusion flags, validated."""
    if kind(path, "annotation file") is None:
        found = sorted(p.name for p in path.parent.glob("*.npy"))
        listed = f" (found: {', '.join(found)})" if found else ""
        raise FileNotFoundError(f"missing annotation file {path}{listed}")
    data = load_npy(path)
    if not isinstance(data, dict) or not {"coords", "visibility"} <= set(data):
        keys = sorted(map(str, data)) if isinstance(data, dict) else type(data).__name__
        raise ValueError(f"{path}: expected a dict with 'coords' and 'visibility', got {keys}")
    try:
        coords = np.asarray(data["coords"])
        occluded = np.asarray(data["visibility"])
    except (ValueError, TypeError) as error:  # ragged lists
        raise ValueError(f"{path}: 'coords' and 'visibility' must be arrays ({error})") from None
    if coords.ndim != 3 or coords.shape[1:] != (num_frames, 2):
        raise ValueError(
            f"{path}: 'coords' must be (N, {num_frames}, 2) for {num_frames} frames, "
            f"got {coords.shape}"
        )
    if occluded.shape != coords.shape[:2]:
        raise ValueError(
            f"{path}: 'visibility' must be (N, T) = {coords.shape[:2]}, got {occluded.shape}"
        )
    if coords.dtype.kind not in "biuf" or not np.isfinite(coords).all():
        raise ValueError(f"{path}: 'coords' must hold finite real numbers")
    if occluded.dtype.kind not in "biuf":
        raise ValueError(f"{path}: 'visibility' must hold booleans, got dtype {occluded.dtype}")
    with np.errstate(over="ignore"):
        coords = coords.astype(np.float32)
    if not np.isfinite(coords).all():  # finite in float64, beyond float32's range
        raise ValueError(f"{path}: 'coords' holds values too large for pixel coordinates")
    return coords, occluded.astype(bool)


def read_sequence(folder: str | os.PathLike[str], *, bgr: bool = False) -> TrackingSample:
    """Reads one sequence folder.

    Points outside the image ([0, W − 1] × [0, H − 1]) are marked not visible, as TAPTR's
    loader does.

    Args:
        folder: ``<root>/<seq>`` with ``frames/`` and ``<seq>.npy``.
        bgr: keep OpenCV's BGR channel order. The official TAPTRv2 training loader does this
            (spec §5.1; almost certainly unintended, since evaluation feeds RGB); only for
            reproducing that recipe.

    Returns:
        video (T, H, W, 3) uint8, tracks (T, N, 2) float32 pixels, visible (T, N) bool,
        named after the folder.

    Raises:
        FileNotFoundError: a frame folder or the annotation file is missing.
        ValueError: a malformed file; the message names it.
    """
    folder = Path(folder)
    paths = _frame_paths(folder)
    video = _read_frames(paths, bgr)
    coords, occluded = _read_annotations(folder / f"{folder.name}.npy", len(paths))
    tracks = coords.transpose(1, 0, 2)  # (N, T, 2) → (T, N, 2)
    height, width = video.shape[1:3]
    inside = (
        (tracks[..., 0] >= 0)
        & (tracks[..., 0] <= width - 1)
        & (tracks[..., 1] >= 0)
        & (tracks[..., 1] <= height - 1)
    )
    visible = ~occluded.T & inside
    return TrackingSample(
        np.ascontiguousarray(video), np.ascontiguousarray(tracks), visible, folder.name
    )


def write_sequence(folder: str | os.PathLike[str], sample: TrackingSample) -> Path:
    """Writes a sample in this layout (frames ``{:03d}.png``, annotations last, atomically).

    Args:
        folder: the sequence folder to create; its name names the ``.npy`` file.
        sample: RGB video (T, H, W, 3) uint8, tracks (T, N, 2), visible (T, N).

    Returns:
        The folder.
    """
    folder = Path(folder)
    frames_dir = folder / FRAMES_DIR
    frames_dir.mkdir(parents=True, exist_ok=True)
    for index, frame in enumerate(sample.video):
        if not cv2.imwrite(str(frames_dir / f"{index:03d}.png"), frame[..., ::-1]):
            raise OSError(f"could not write {frames_dir / f'{index:03d}.png'}")
    annotations = {
        "coords": np.ascontiguousarray(sample.tracks.transpose(1, 0, 2), dtype=np.float32),
        "visibility": np.ascontiguousarray(~sample.visible.T),  # the layout stores occlusion
    }
    # written last, so a folder with its .npy is complete
    with atomic_path(folder / f"{folder.name}.npy") as tmp, tmp.open("wb") as stream:
        np.save(stream, np.array(annotations, dtype=object), allow_pickle=True)
    return folder
