"""Validation and normalisation of what users pass to the predictor.

Every check raises a one-line ValueError that names the problem (shape, dtype, range,
NaN), so that the CLI can print it without a traceback.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

# re-exported: the point limit is part of this module's interface
from taptr.task.query_checks import MAX_POINTS_ENV as MAX_POINTS_ENV
from taptr.task.query_checks import check_num_points as check_num_points
from taptr.task.query_checks import check_query_values, grid_points
from taptr.task.query_checks import max_points as max_points

RESULT_BYTES_PER_POINT_FRAME = 16
"""Bytes of the result per point and frame: float32 (x, y), logit and visibility (padded)."""


def video_tensor(video: np.ndarray | Tensor) -> Tensor:
    """Brings a video to (B, T, 3, H, W), uint8 or float in [0, 1], without copying it.

    Frames stay in their input type (a float copy of a long video would take four times
    its memory); `as_unit_float` converts them window by window.

    Args:
        video: a uint8 numpy array (T, H, W, 3), or a torch tensor (B, T, 3, H, W) of
            uint8 or of floats in [0, 1].
    """
    if isinstance(video, np.ndarray):
        if video.ndim != 4 or video.shape[-1] != 3:
            raise ValueError(f"a numpy video must be (T, H, W, 3), got shape {video.shape}")
        if video.dtype != np.uint8:
            raise ValueError(f"a numpy video must be uint8, got {video.dtype}")
        return torch.from_numpy(video).permute(0, 3, 1, 2)[None]  # a view: (1, T, 3, H, W)
    if not isinstance(video, Tensor):
        raise ValueError(
            f"video must be a numpy array, a torch tensor or a path, got {type(video).__name__}"
        )
    if video.dim() != 5 or video.shape[2] != 3:
        raise ValueError(f"a tensor video must be (B, T, 3, H, W), got shape {tuple(video.shape)}")
    if video.dtype == torch.uint8:
        return video
    if not video.is_floating_point():
        raise ValueError(f"a tensor video must be uint8 or float, got {video.dtype}")
    if video.numel() and not bool(torch.isfinite(video).all()):
        raise ValueError("the video contains NaN or infinite values")
    if video.numel() and (float(video.max()) > 1 or float(video.min()) < 0):
        raise ValueError("a float video must lie in [0, 1]; pass uint8 frames or divide by 255")
    return video


def as_unit_float(frames: Tensor) -> Tensor:
    """uint8 frames → float32 in [0, 1]; float frames are returned as float32."""
    return frames.float() / 255 if frames.dtype == torch.uint8 else frames.float()


def query_tensor(
    queries: np.ndarray | Tensor, batch: int, num_frames: int | None, height: int, width: int
) -> Tensor:
    """Validates (t, x, y) pixel queries and returns them as (B, N, 3) float32.

    Args:
        queries: (N, 3) or (B, N, 3) as (t, x, y): frame index and pixel position with
            pixel centres at integers.
        batch: number of videos B.
        num_frames: frames T of the video; None for a stream of unknown length (no upper
            bound on t, and results are not held, so their memory is not checked).
        height: frame height H in pixels.
        width: frame width W in pixels.

    Raises:
        ValueError: queries that are not real numbers (text, objects, complex, bool), of
            the wrong shape, non-finite or outside the video; more than `max_points`
            points; or results that would not fit in the available memory.
    """
    q = _real_tensor(queries).detach().to("cpu", torch.float64)
    if q.shape == (0,):  # an empty list: no queries
        q = q.reshape(0, 3)
    if q.dim() == 2:
        q = q[None].expand(batch, -1, -1)
    if q.dim() != 3 or q.shape[-1] != 3 or q.shape[0] != batch:
        raise ValueError(
            f"queries must be (N, 3) or (B={batch}, N, 3) as (t, x, y), got {tuple(q.shape)}"
        )
    check_num_points(q.shape[1])
    if num_frames is not None:
        check_result_memory(batch, num_frames, q.shape[1])
    check_query_values(q.numpy(), num_frames, height, width)
    return q.float()


def grid_queries(
    grid_size: int, frame: int, height: int, width: int, *, name: str = "grid_size"
) -> Tensor:
    """`taptr.task.query_checks.grid_points` as a tensor, (N, 3) float32 (t, x, y)."""
    return torch.from_numpy(grid_points(grid_size, frame, height, width, name=name))


def check_result_memory(batch: int, num_frames: int, num_points: int) -> None:
    """Raises a ValueError when the results alone would not fit in the available memory.

    A cheap lower bound, checked before any window runs: the (B, T, N) tracks, logits and
    visibility. The decoder needs more on top, so passing this check does not promise that
    the run fits.
    """
    needed = batch * num_frames * num_points * RESULT_BYTES_PER_POINT_FRAME
    available = _available_memory()
    if available is not None and needed > available:
        raise ValueError(
            f"tracking {num_points:,} points through {batch * num_frames:,} frames needs "
            f"{needed / 2**30:.1f} GiB for the results alone, more than the "
            f"{available / 2**30:.1f} GiB of memory available; track fewer points or frames"
        )


def _available_memory() -> int | None:
    """Bytes of memory the system reports available (Linux), or None where it does not say."""
    try:
        with open("/proc/meminfo") as stream:
            for line in stream:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _real_tensor(queries: Any) -> Tensor:
    """Queries as a tensor of real numbers; strings, objects, complex and bools are refused."""
    expected = "queries must be an (N, 3) or (B, N, 3) array of real numbers (t, x, y)"
    if isinstance(queries, Tensor):
        if queries.is_complex() or queries.dtype == torch.bool:
            raise ValueError(f"{expected}, got a {queries.dtype} tensor")
        return queries
    try:
        array = np.asarray(queries)
    except (TypeError, ValueError):  # ragged nested lists, odd objects
        raise ValueError(f"{expected}, got rows of different lengths") from None
    if array.dtype.kind not in "iuf":
        raise ValueError(f"{expected}, got {_describe(array)}")
    return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float64))


def _describe(array: np.ndarray) -> str:
    kinds = {"U": "text", "S": "bytes", "O": "Python objects", "c": "complex numbers"}
    return kinds.get(array.dtype.kind, f"dtype {array.dtype}")
