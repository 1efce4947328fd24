"""What the demo page sends, checked and turned into API inputs: videos, points, masks, queries.

Every problem with a user's input raises `DemoError` with one sentence meant for the person
at the page (the page shows it as is): a file that is not a video or cannot be decoded, a
video over the frame or resolution limits, no points selected, an empty painted region.

Conventions are the package's: frames are (H, W, 3) uint8 RGB, a video is (T, H, W, 3),
positions are (x, y) pixels with pixel centres at integers, queries are (t, x, y), and masks
are (H, W) bool, True inside the region.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from taptr.api.inputs import grid_queries
from taptr.api.regions import sample_region_queries
from taptr.apps.demo.settings import Limits
from taptr.data.sample_video import make_sample_clip
from taptr.io.image_guard import read_image_channels
from taptr.io.video import read_video, video_info, write_video
from taptr.viz.draw import default_radius, draw_frame, point_colors

Point = tuple[int, float, float]
"""A clicked query point (t, x, y): frame index and pixel position, pixel centres at integers."""

PREVIEW_MIN_RADIUS = 3.0
"""Smallest radius in pixels of a clicked point on the query frame, so small videos show it."""

QUERY_MODES = ("points", "region", "grid")
"""How the tracking tab picks its queries: clicked points, a painted region, or a grid."""


class DemoError(ValueError):
    """A problem with what the user gave the demo; its message is shown on the page."""


@dataclass(frozen=True)
class LoadedVideo:
    """A video read for the demo.

    Attributes:
        frames: (T, H, W, 3) uint8 RGB frames, at most ``Limits.max_frames`` of them.
        fps: frames per second (24 when the file does not say).
        name: the file name shown to the user.
        message: one line describing the video, including any cut to the frame limit.
    """

    frames: np.ndarray
    fps: float
    name: str
    message: str


def load_video(
    path: str | os.PathLike[str], limits: Limits, name: str | None = None
) -> LoadedVideo:
    """Reads an uploaded or sample video within the limits.

    Args:
        path: the video file.
        limits: frame and resolution limits.
        name: the name to show in messages (uploads live under generated temporary names).

    Raises:
        DemoError: unsupported type, unreadable or corrupt file, no frames, or a frame
            larger than ``limits.max_side``.
    """
    source = Path(path)
    shown = name or source.name
    try:
        info = video_info(source)
        if max(info.height, info.width) > limits.max_side:
            raise DemoError(
                f"{shown} is {info.width}×{info.height}; the demo accepts videos up to "
                f"{limits.max_side} pixels on the longer side (taptr demo --max-side)"
            )
        # One frame past the limit tells whether the video was cut, even when the
        # container does not state its frame count.
        frames = read_video(source, max_frames=limits.max_frames + 1)
    except (ValueError, FileNotFoundError) as error:
        if isinstance(error, DemoError):
            raise
        # The upload's temporary path means nothing to the user: name the file instead.
        raise DemoError(str(error).replace(str(source), shown)) from None
    fps = info.fps or 24.0
    num_frames, height, width = frames.shape[:3]
    message = f"{shown}: {min(num_frames, limits.max_frames)} frames of {width}×{height}"
    if num_frames > limits.max_frames:
        total = f" of {info.num_frames}" if info.num_frames else ""
        message += (
            f" (the first {limits.max_frames}{total} frames; the demo's limit is "
            f"{limits.max_frames}, taptr demo --max-frames)"
        )
        frames = frames[: limits.max_frames]
    return LoadedVideo(frames, fps, shown, message)


def _generated(num_frames: int, size: int) -> Callable[[Path], Path]:
    def write(folder: Path) -> Path:
        target = folder / f"taptr-sample-{num_frames}x{size}.mp4"
        if target.is_file():  # written atomically, so an existing file is complete
            return target
        clip = make_sample_clip(num_frames=num_frames, height=size, width=size)
        return write_video(target, clip.video, clip.fps)

    return write


SAMPLES: Mapping[str, Callable[[Path], Path]] = {
    "taptr sample clip (48 frames, 256×256)": _generated(48, 256),
    "taptr sample clip, short (16 frames, 128×128)": _generated(16, 128),
}
"""Bundled samples: name → function writing the clip into a folder and returning its path.

Both are the package's own procedural clip (`taptr.data.sample_video`): licence-clean and
made on the spot, so nothing ships and nothing is downloaded.
"""


def read_paste_image(path: str | os.PathLike[str]) -> np.ndarray:
    """The uploaded image to paste, read the guarded way: header first, within the limits.

    Returns:
        (h, w, 3) RGB or (h, w, 4) RGBA uint8.

    Raises:
        DemoError: not an image taptr reads, or above the ``image_pixels`` limit (the
            message does not show the server's temporary path).
    """
    try:
        image = read_image_channels(path, "the image to paste")
    except (ValueError, FileNotFoundError) as error:
        raise DemoError(str(error)) from None
    if image.ndim == 2:  # grey, 8 or 16 bits or float: shown as grey RGB
        grey = image if image.dtype == np.uint8 else np.clip(image / 257, 0, 255)
        return np.repeat(grey.astype(np.uint8)[..., None], 3, axis=2)
    if image.shape[2] == 2:  # grey + alpha
        return np.concatenate([np.repeat(image[..., :1], 3, axis=2), image[..., 1:]], axis=2)
    return image


def add_point(points: Sequence[Point], point: Point, limits: Limits) -> list[Point]:
    """A new list with ``point`` appended; refuses more than ``limits.max_points``."""
    if len(points) >= limits.max_points:
        raise DemoError(f"the demo tracks at most {limits.max_points} points (--max-points)")
    return [*points, point]


def click_to_point(index: Sequence[int], frame: int) -> Point:
    """The query point of a click on the query frame's image.

    Gradio 6 reports a click as the *rounded* position measured from the image's top-left
    corner, in image pixels (its ``SelectData.index``, [column, row]). That corner is at
    (-0.5, -0.5) when pixel centres are at integers, so subtracting 0.5 gives the pixel
    position within ±0.5 px, where using the index as is would lean half a pixel right
    and down.

    Args:
        index: [column, row] from the select event.
        frame: the query frame t shown when the user clicked.

    Returns:
        (t, x, y) with (x, y) in pixels, pixel centres at integers.
    """
    column, row = (float(v) for v in index[:2])
    return int(frame), column - 0.5, row - 0.5


def preview_frame(frames: np.ndarray, frame: int, points: Sequence[Point]) -> np.ndarray:
    """Frame ``frame`` with the clicked points that belong to it drawn as discs.

    Each point gets the colour it will have in the tracking overlay (both use
    `point_colors` of the query positions), so the user can tell them apart afterwards.

    Args:
        frames: (T, H, W, 3) uint8 RGB video.
        frame: the frame index t to show.
        points: all clicked points (t, x, y); only those with this t are drawn.

    Returns:
        (H, W, 3) uint8 RGB image.
    """
    if not 0 <= frame < len(frames):
        raise DemoError(f"frame {frame} outside [0, {len(frames) - 1}]")
    image = frames[frame]
    if not points:
        return image.copy()
    queries = np.asarray(points, dtype=np.float64)  # (N, 3) as (t, x, y)
    here = queries[:, 0] == frame
    positions = queries[None, :, 1:]  # (1, N, 2): a one-frame track per point
    # Larger than the overlay's points: these are targets the user has to find again.
    radius = max(PREVIEW_MIN_RADIUS, 1.6 * default_radius(*image.shape[:2]))
    return draw_frame(
        image,
        positions,
        np.ones((1, len(queries)), bool),
        point_colors(queries[:, 1:]),
        active=here[None],
        radius=radius,
    )


def mask_from_editor(value: Mapping[str, Any] | None, height: int, width: int) -> np.ndarray:
    """The painted region of an image-editor value as an (H, W) bool mask.

    Args:
        value: Gradio's ImageEditor value with ``type="numpy"``: a mapping whose
            ``"layers"`` is a list of (h, w, 4) RGBA (or (h, w, 3)) uint8 paint layers
            over the frame; None when nothing was sent.
        height: frame height H in pixels.
        width: frame width W in pixels.

    Returns:
        (H, W) bool, True wherever any layer has paint. A layer of another size (the
        editor's canvas) is resized to the frame, nearest neighbour.
    """
    mask = np.zeros((height, width), bool)
    for layer in (value or {}).get("layers") or []:
        array = np.asarray(layer)
        if array.ndim != 3 or array.shape[2] not in (3, 4):
            raise DemoError(f"unexpected paint layer of shape {array.shape}")
        painted = np.asarray(array[..., 3] > 0 if array.shape[2] == 4 else array.any(axis=2))
        if painted.shape != (height, width):
            as_bytes = np.ascontiguousarray(painted, dtype=np.uint8)
            painted = cv2.resize(as_bytes, (width, height), interpolation=cv2.INTER_NEAREST) > 0
        mask |= painted
    return mask


def build_queries(
    mode: str,
    *,
    video_shape: tuple[int, ...],
    query_frame: int,
    limits: Limits,
    points: Sequence[Point] = (),
    mask: np.ndarray | None = None,
    grid_size: int = 8,
    region_stride: int = 8,
) -> np.ndarray:
    """The (N, 3) queries for the chosen mode.

    Args:
        mode: one of `QUERY_MODES`.
        video_shape: (T, H, W, ...) of the video.
        query_frame: frame t of the region and grid modes.
        limits: the point limit.
        points: clicked points (t, x, y), for mode "points".
        mask: (H, W) bool painted region on ``query_frame``, for mode "region".
        grid_size: points per side of the grid, for mode "grid".
        region_stride: pixel spacing of the points sampled in the region.

    Returns:
        (N, 3) float32 queries (t, x, y), (x, y) in pixels.

    Raises:
        DemoError: an unknown mode, no points, an empty region, or too many points.
    """
    num_frames, height, width = video_shape[:3]
    if not 0 <= query_frame < num_frames:
        raise DemoError(f"query frame {query_frame} outside [0, {num_frames - 1}]")
    if mode == "points":
        if not points:
            raise DemoError(
                "no points selected: click on the query frame to add points, "
                "or choose the region or grid mode"
            )
        queries = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    elif mode == "region":
        if mask is None or not mask.any():
            raise DemoError("no region painted: paint over the query frame with the brush")
        queries = sample_region_queries(
            mask, query_frame, stride=region_stride, max_points=limits.max_points
        )
    elif mode == "grid":
        if not 1 <= grid_size * grid_size <= limits.max_points:
            raise DemoError(
                f"a {grid_size}×{grid_size} grid exceeds the limit of {limits.max_points} points"
            )
        queries = grid_queries(grid_size, query_frame, height, width).numpy()
    else:
        raise DemoError(f"unknown query mode {mode!r}; choose one of {', '.join(QUERY_MODES)}")
    if len(queries) > limits.max_points:
        raise DemoError(f"{len(queries)} points exceed the limit of {limits.max_points}")
    return queries.astype(np.float32)
