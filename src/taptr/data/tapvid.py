"""Readers of the TAP-Vid evaluation sets: DAVIS, RGB-Stacking, Kinetics and RoboTAP.

Every set is one or more pickles of items ``{"video", "points", "occluded"}``: ``video`` is
(T, H, W, 3) uint8, or (Kinetics) a sequence of T JPEG-encoded frames; ``points`` is
(N, T, 2) normalised *raster* (x, y), where (0, 0) is the top-left corner of the top-left
pixel and (1, 1) the bottom-right corner of the bottom-right one; ``occluded`` is (N, T) bool.
A pickle holds a dict name → item (DAVIS, RoboTAP) or a list of items (RGB-Stacking, each
Kinetics shard); unnamed videos are named by their index in the set.

Files are read with the restricted unpickler of `taptr.io.safe_pickle` only, so a crafted
file cannot run code. Videos are handed out as `PendingVideo` entries whose ``load`` builds
the `TrackingSample` (decoding JPEG frames then), so one video at a time is decoded.

`raster_to_pixels` and `pixels_to_raster` are the one place where TAP-Vid's raster
coordinates meet taptr's pixel convention (pixel centres at integers).
"""

from __future__ import annotations

import functools
import logging
import math
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from PIL import Image  # noqa: F401  (tests count the frames opened through it)

from taptr.io import limits
from taptr.io.file_kind import kind
from taptr.io.image_guard import open_image, to_rgb
from taptr.io.safe_pickle import load_pickle
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
    if kind(root, f"TAP-Vid {dataset} root") == "file":  # a FIFO or device is refused here
        return [root]
    folder, pattern = LAYOUT[dataset]
    candidates = [root / folder, root]
    for directory in candidates:
        # a FIFO or device named like a dataset file is refused, never opened
        files = sorted(p for p in directory.glob(pattern) if kind(p, "dataset file") == "file")
        if files:
            if dataset == "kinetics" and len(files) != KINETICS_SHARDS:
                logger.warning("found %d of %d Kinetics shards", len(files), KINETICS_SHARDS)
            return files
    looked = " and ".join(str(d / pattern) for d in candidates)
    raise FileNotFoundError(f"no TAP-Vid {dataset} file at {root} (looked for {looked})")


def decode_frames(frames: Any, label: str = "video") -> np.ndarray:
    """(T, H, W, 3) uint8 frames from a uint8 array or a sequence of encoded (png/jpg) frames.

    The frame count and the decoded size (T × H × W × 3 bytes, from the first frame's
    header) are checked against the ``video_frames`` and ``video_bytes`` limits of
    `taptr.io.limits` before any frame is decoded, and every frame's header before it is.

    Args:
        frames: the item's ``video`` entry.
        label: names the video in messages.

    Raises:
        ValueError: malformed or undecodable frames, frames of different sizes, or a video
            over a limit.
    """
    if isinstance(frames, np.ndarray) and frames.dtype == np.uint8 and frames.ndim == 4:
        limits.check("video_frames", len(frames), f"{label}: {len(frames):,} frames")
        return frames
    if isinstance(frames, np.ndarray) and frames.dtype.kind not in "OS":  # objects, bytes
        # a decoded video of another type or shape: not a list of encoded frames either
        raise ValueError(
            f"{label}: 'video' is a {frames.dtype} array of shape {frames.shape}; expected "
            "(T, H, W, 3) uint8 frames or a list of PNG/JPEG-encoded frames"
        )
    if not isinstance(frames, (list, tuple, np.ndarray)) or not len(frames):
        raise ValueError(f"{label}: expected (T, H, W, 3) uint8 frames or a list of png/jpg frames")
    limits.check("video_frames", len(frames), f"{label}: {len(frames):,} frames")
    encoded = [_encoded_frame(frame, f"{label} frame {t}") for t, frame in enumerate(frames)]
    video = None
    for t, data in enumerate(encoded):
        with open_image(data, f"{label} frame {t}") as image:
            size = (image.size[1], image.size[0], 3)
            if video is None:
                # the first header tells the size of every frame: bound the whole video
                needed = len(encoded) * math.prod(size)
                what = f"{label}: {len(encoded)} frames of {size[1]}x{size[0]}"
                limits.check("video_bytes", needed, what)
                video = np.empty((len(encoded), *size), dtype=np.uint8)
            elif size != video.shape[1:]:
                raise ValueError(
                    f"{label} frame {t}: {size[1]}x{size[0]}, the first frame is "
                    f"{video.shape[2]}x{video.shape[1]}"
                )
            video[t] = to_rgb(image, f"{label} frame {t}")
    if video is None:
        raise ValueError(f"{label}: no frames")
    return video


def _encoded_frame(frame: Any, label: str) -> bytes:
    """The bytes of one encoded frame; refuses anything else (``bytes(n)`` would allocate)."""
    if isinstance(frame, np.ndarray) and frame.dtype == np.uint8 and frame.ndim == 1:
        return frame.tobytes()
    if isinstance(frame, (bytes, bytearray)):
        return bytes(frame)
    raise ValueError(f"{label}: an encoded frame must be bytes, got {type(frame).__name__}")


def _numbers(value: Any, label: str, key: str) -> np.ndarray:
    """``value`` as a float64 array of finite real numbers."""
    try:
        array = np.asarray(value)
    except (ValueError, TypeError) as error:  # ragged lists
        raise ValueError(f"{label}: {key!r} is not an array ({error})") from None
    if array.dtype.kind not in "biuf":
        raise ValueError(f"{label}: {key!r} must hold real numbers, got dtype {array.dtype}")
    array = array.astype(np.float64)
    if not np.isfinite(array).all():
        raise ValueError(f"{label}: {key!r} holds non-finite values (NaN or inf)")
    return array


def item_to_sample(item: Any, name: str, source: str) -> TrackingSample:
    """Builds the `TrackingSample` of one item; tracks in pixels, visibility not occlusion.

    The ground truth is checked (shapes, finite numbers) before the frames are decoded.

    Args:
        item: the ``{"video", "points", "occluded"}`` mapping of the file.
        name: the video's name.
        source: the file it comes from, for messages.
    """
    label = f"{source}: video {name!r}"
    if not isinstance(item, Mapping) or not {"video", "points", "occluded"} <= set(item):
        raise ValueError(f"{label} is not a {{'video', 'points', 'occluded'}} mapping")
    points = _numbers(item["points"], label, "points")
    occluded = _numbers(item["occluded"], label, "occluded").astype(bool)
    try:
        num_frames = len(item["video"])
    except TypeError:
        raise ValueError(f"{label}: 'video' is a {type(item['video']).__name__}") from None
    if num_frames < 1:
        raise ValueError(f"{label}: no frames")
    if (
        points.ndim != 3
        or points.shape[1:] != (num_frames, 2)
        or occluded.shape != points.shape[:2]
    ):
        raise ValueError(
            f"{label}: {num_frames} frames but points {points.shape} and occluded "
            f"{occluded.shape} (expected (N, T, 2) and (N, T))"
        )
    video = decode_frames(item["video"], label)
    if video.ndim != 4 or video.shape[3] != 3 or not video.size:
        raise ValueError(f"{label}: expected a video (T, H, W, 3), got {video.shape}")
    height, width = video.shape[1:3]
    with np.errstate(over="ignore"):
        tracks = raster_to_pixels(points.transpose(1, 0, 2), height, width).astype(np.float32)
    if not np.isfinite(tracks).all():  # finite in float64, beyond float32's range
        raise ValueError(f"{label}: 'points' holds values too large for pixel coordinates")
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
