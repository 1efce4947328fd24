"""Readers of the TAP-Vid evaluation sets: DAVIS, RGB-Stacking, Kinetics and RoboTAP.

Every set is one or more pickles of items ``{"video", "points", "occluded"}``: ``video`` is
(T, H, W, 3) uint8, or (Kinetics) a sequence of T JPEG-encoded frames; ``points`` is
(N, T, 2) normalised *raster* (x, y), where (0, 0) is the top-left corner of the top-left
pixel and (1, 1) the bottom-right corner of the bottom-right one; ``occluded`` is (N, T) bool.
A pickle holds a dict name → item (DAVIS, RoboTAP) or a list of items (RGB-Stacking, each
Kinetics shard); unnamed videos are named by their index in the set.

Files are read with the restricted unpickler of `taptr.data.safe_pickle` only, so a crafted
file cannot run code. Videos are handed out as `PendingVideo` entries whose ``load`` builds
the `TrackingSample` (decoding JPEG frames then), so one video at a time is decoded.

`raster_to_pixels` and `pixels_to_raster` are the one place where TAP-Vid's raster
coordinates meet taptr's pixel convention (pixel centres at integers).
"""

from __future__ import annotations

import functools
import io
import logging
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from PIL import Image

from taptr.data.safe_pickle import load_pickle
from taptr.types import TrackingSample

logger = logging.getLogger(__name__)

LAYOUT = {
    "davis": ("tapvid_davis", "tapvid_davis.pkl"),
    "kinetics": ("tapvid_kinetics", "*_of_0010.pkl"),
    "rgb_stacking": ("tapvid_rgb_stacking", "tapvid_rgb_stacking.pkl"),
    "robotap": ("tapvid_robotap", "robotap_split*.pkl"),
}
"""Per set: the folder and file name (or glob) of CoTracker's layout ``<root>/<folder>/<file>``."""

TAPVID_DATASETS = tuple(LAYOUT)
KINETICS_SHARDS = 10


class PendingVideo(NamedTuple):
    """A video of a dataset, not yet loaded.

    Attributes:
        name: the video's name (its dict key, sequence name, or index in the set).
        load: builds the `TrackingSample`; decoding happens here.
    """

    name: str
    load: Callable[[], TrackingSample]


def raster_to_pixels(points: np.ndarray, height: int, width: int) -> np.ndarray:
    """Normalised raster (x, y) → pixels with centres at integers: ``raster × size − 0.5``.

    Args:
        points: (..., 2) as (x, y), 0 and 1 at the outer edges of the image.
        height: image height H in pixels.
        width: image width W in pixels.
    """
    return np.asarray(points) * np.array([width, height], dtype=np.float64) - 0.5


def pixels_to_raster(points: np.ndarray, height: int, width: int) -> np.ndarray:
    """Inverse of `raster_to_pixels`: (..., 2) (x, y) pixels → normalised raster (x, y)."""
    return (np.asarray(points, dtype=np.float64) + 0.5) / np.array([width, height])


def find_tapvid_files(dataset: str, root: str | os.PathLike[str]) -> list[Path]:
    """The pickle files of a set: ``root`` itself, or found in CoTracker's folder layout.

    Args:
        dataset: one of `TAPVID_DATASETS`.
        root: a dataset file, the set's folder (e.g. ``tapvid_davis/``) or the folder above it.

    Raises:
        FileNotFoundError: nothing matching exists (the message lists where it looked).
    """
    if dataset not in LAYOUT:
        raise ValueError(f"unknown TAP-Vid set {dataset!r}; expected one of {TAPVID_DATASETS}")
    root = Path(root)
    if root.is_file():
        return [root]
    folder, pattern = LAYOUT[dataset]
    candidates = [root / folder, root]
    for directory in candidates:
        files = sorted(p for p in directory.glob(pattern) if p.is_file())
        if files:
            if dataset == "kinetics" and len(files) != KINETICS_SHARDS:
                logger.warning("found %d of %d Kinetics shards", len(files), KINETICS_SHARDS)
            return files
    looked = " and ".join(str(d / pattern) for d in candidates)
    raise FileNotFoundError(f"no TAP-Vid {dataset} file at {root} (looked for {looked})")


def decode_frames(frames: Any) -> np.ndarray:
    """(T, H, W, 3) uint8 frames from a uint8 array or a sequence of JPEG-encoded frames."""
    if isinstance(frames, np.ndarray) and frames.dtype == np.uint8:
        return frames
    decoded = []
    for frame in frames:
        with Image.open(io.BytesIO(bytes(frame))) as image:
            decoded.append(np.asarray(image.convert("RGB")))
    return np.stack(decoded)


def item_to_sample(item: Any, name: str, source: str) -> TrackingSample:
    """Builds the `TrackingSample` of one item; tracks in pixels, visibility not occlusion.

    Args:
        item: the ``{"video", "points", "occluded"}`` mapping of the file.
        name: the video's name.
        source: the file it comes from, for messages.
    """
    label = f"{source}: video {name!r}"
    if not isinstance(item, Mapping) or not {"video", "points", "occluded"} <= set(item):
        raise ValueError(f"{label} is not a {{'video', 'points', 'occluded'}} mapping")
    try:
        video = decode_frames(item["video"])
    except (OSError, TypeError, ValueError) as error:
        raise ValueError(f"{label}: cannot decode the frames ({error})") from None
    points = np.asarray(item["points"], dtype=np.float64)
    occluded = np.asarray(item["occluded"], dtype=bool)
    if video.ndim != 4 or points.ndim != 3 or points.shape[2] != 2:
        raise ValueError(
            f"{label}: expected video (T, H, W, 3) and points (N, T, 2), got "
            f"{video.shape} and {points.shape}"
        )
    if occluded.shape != points.shape[:2] or points.shape[1] != video.shape[0]:
        raise ValueError(
            f"{label}: {video.shape[0]} frames but points {points.shape} and occluded "
            f"{occluded.shape} (expected (N, T, 2) and (N, T))"
        )
    height, width = video.shape[1:3]
    tracks = raster_to_pixels(points.transpose(1, 0, 2), height, width).astype(np.float32)
    return TrackingSample(video, tracks, ~occluded.T, name)


def _entries(data: Any, source: Path, first_index: int) -> Sequence[tuple[str, Any]]:
    """(name, item) pairs of one unpickled file."""
    if isinstance(data, Mapping):
        return [(str(name), item) for name, item in data.items()]
    if isinstance(data, (list, tuple)):
        return [(str(first_index + k), item) for k, item in enumerate(data)]
    raise ValueError(f"{source} holds a {type(data).__name__}, expected a dict or a list of videos")


def iter_tapvid(dataset: str, root: str | os.PathLike[str]) -> Iterator[PendingVideo]:
    """The videos of a TAP-Vid set in file order, one file in memory at a time.

    The files are looked up at once (a missing file fails here, not on first use).

    Args:
        dataset: one of `TAPVID_DATASETS`.
        root: see `find_tapvid_files`.
    """
    return _iter_files(find_tapvid_files(dataset, root))


def _iter_files(paths: list[Path]) -> Iterator[PendingVideo]:
    index = 0
    for path in paths:
        entries = _entries(load_pickle(path), path, index)
        index += len(entries)
        for name, item in entries:
            yield PendingVideo(name, functools.partial(item_to_sample, item, name, str(path)))
