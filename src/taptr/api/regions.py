"""Query points from a region: a mask image read by a fixed rule, sampled on a grid.

A region is given as a mask drawn on one frame (the query frame): `read_mask` reads the
image (safely, within the image limits of `taptr.io.image_guard`) and `sample_region_queries`
turns it into (t, x, y) queries on a regular pixel grid inside it. ``taptr track --mask``,
``taptr edit``, region editing (`taptr.apps.editing`) and corpus query specs
(`taptr.corpus.inputs`) build their queries here. No torch is imported: a bad mask is
reported before the model loads.

Coordinates are (x, y) pixels with pixel centres at integers; masks are (H, W) bool, True
inside the region.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from taptr.io.file_kind import kind, require_file
from taptr.io.image_guard import STILL_FORMATS, NotAnImageError, read_image_channels


def read_mask(
    path: str | os.PathLike[str], *, name: str = "mask", size: tuple[int, int] | None = None
) -> np.ndarray:
    """Reads a mask image as an (H, W) bool array, True inside the region.

    The rule: a pixel is inside when it is not black and not transparent, that is when
    any colour channel is non-zero and its alpha (in images that have one) is non-zero.
    So a white-on-black mask, a 0/1-valued PNG and a region painted on a transparent
    layer all read as drawn; anti-aliased edges count as inside.

    Args:
        path: image file (PNG recommended; JPEG, BMP, TIFF, WebP and PPM are read too,
            through `taptr.io.image_guard`: header first, within the ``image_pixels`` limit).
        name: what messages call the file, e.g. ``"--mask"`` for the command line.
        size: (height, width) the mask must have (the video's), or None for any.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file, when it is not a regular file or not an image, exceeds
            the ``image_pixels`` limit, has another size than ``size`` or no pixel is inside.
    """
    source = Path(path)
    if kind(source, name) is None:
        raise FileNotFoundError(f"{name} {source}: file not found")
    require_file(source, name)
    try:
        image = read_image_channels(source, f"{name} {source}")
    except NotAnImageError:
        raise ValueError(
            f"{name} {source}: not an image taptr reads ({', '.join(STILL_FORMATS)}); use a PNG"
        ) from None
    height, width = image.shape[:2]
    if size is not None and (height, width) != tuple(size):
        raise ValueError(f"{name} {source} is {width}x{height}, the video is {size[1]}x{size[0]}")
    mask = _inside(image)
    if not mask.any():
        raise ValueError(
            f"{name} {source}: no pixel is inside the region (inside = not black and not "
            "transparent)"
        )
    return mask


def _inside(image: np.ndarray) -> np.ndarray:
    """Pixels that are neither black nor transparent: grey, grey + alpha, RGB or RGBA."""
    if image.ndim == 2:
        return image != 0
    channels = image.shape[2]
    colour = image[..., : 3 if channels >= 3 else 1]
    inside = (colour != 0).any(axis=-1)
    if channels in (2, 4):  # grey + alpha, BGRA
        inside &= image[..., -1] != 0
    return inside


def sample_region_queries(
    mask: np.ndarray, query_frame: int, *, stride: int = 8, max_points: int | None = None
) -> np.ndarray:
    """Samples query points on a regular grid inside a region.

    The grid has a spacing of ``stride`` pixels and is centred on the region's bounding box.
    A region too small to hold a grid point gets one point, the region pixel nearest to its
    centroid. With ``max_points``, a larger sample is thinned evenly along the raster order.

    Args:
        mask: (H, W) bool, True inside the region.
        query_frame: frame index t the mask was drawn on.
        stride: grid spacing in pixels.
        max_points: the most points to return; None for no limit.

    Returns:
        (N, 3) float32 queries (t, x, y), (x, y) in pixels, in raster order.
    """
    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 2 or not mask.any():
        raise ValueError(f"mask must be a non-empty (H, W) bool array, got shape {mask.shape}")
    if stride < 1 or (max_points is not None and max_points < 1):
        raise ValueError(f"stride and max_points must be >= 1, got {stride} and {max_points}")
    ys, xs = np.nonzero(mask)
    grid_x = _centred_grid(xs.min(), xs.max(), stride)
    grid_y = _centred_grid(ys.min(), ys.max(), stride)
    gy, gx = np.meshgrid(grid_y, grid_x, indexing="ij")
    inside = mask[gy, gx]
    points = np.column_stack([gx[inside], gy[inside]])
    if len(points) == 0:
        nearest = np.argmin((xs - xs.mean()) ** 2 + (ys - ys.mean()) ** 2)
        points = np.array([[xs[nearest], ys[nearest]]])
    if max_points is not None and len(points) > max_points:
        points = points[np.linspace(0, len(points) - 1, max_points).round().astype(np.int64)]
    times = np.full((len(points), 1), query_frame)
    return np.hstack([times, points]).astype(np.float32)


def _centred_grid(low: int, high: int, stride: int) -> np.ndarray:
    """Integer grid positions with spacing ``stride``, centred in [low, high]."""
    count = (high - low) // stride + 1
    start = low + ((high - low) - (count - 1) * stride) // 2
    return start + stride * np.arange(count)
