"""Checks of (t, x, y) query points that need numpy only, not torch.

The predictor's input validation (`taptr.api.inputs.query_tensor`) and the command line's
checks before the model loads share these, so that a query outside the video or too many
points fail in a fraction of a second with the same message either way: importing torch
alone takes seconds and most of a gigabyte.
"""

from __future__ import annotations

import operator
from typing import Any

import numpy as np

from taptr.io.limits import LIMITS, limit

MAX_POINTS_ENV = LIMITS["points"].variable
"""Environment variable that raises the most query points per call (read at every call).

The default, ``LIMITS["points"].default`` (100,000, ten times the 10k-point benchmark),
keeps a call within the memory of ordinary machines: each point costs memory in every
window of the decoder and in the results.
"""


def max_points() -> int:
    """The most points per call: 100,000, or the value of `MAX_POINTS_ENV` when set."""
    return limit("points")


def check_num_points(count: int, what: str = "queries") -> None:
    """Raises a ValueError, saying how to raise the limit, when ``count`` > `max_points`.

    Args:
        count: number of points asked for.
        what: what asked for them, for the message (``"--grid 1000"``, a file name, ...).
    """
    most = max_points()
    if count > most:
        raise ValueError(
            f"{what}: {count:,} points, more than the limit of {most:,} per call; track "
            f"them in batches, or set the environment variable {MAX_POINTS_ENV}={count} "
            "if this machine has the memory"
        )


def check_query_values(
    queries: np.ndarray, num_frames: int | None, height: int, width: int
) -> None:
    """Raises a ValueError for queries that are not finite, whole frames, inside the video.

    Args:
        queries: (..., 3) float64 (t, x, y) with pixel centres at integers.
        num_frames: frames T of the video; None for no upper bound on t.
        height: frame height H in pixels.
        width: frame width W in pixels.
    """
    if not np.isfinite(queries).all():
        raise ValueError("queries contain NaN or infinite values")
    t, x, y = queries[..., 0], queries[..., 1], queries[..., 2]
    if (t != np.round(t)).any():
        raise ValueError("query frames t must be whole frame indices")
    end = float("inf") if num_frames is None else num_frames
    if t.size and (t.min() < 0 or t.max() >= end):
        raise ValueError(f"query frame t outside [0, {end}) (got {int(t.min())}..{int(t.max())})")
    # pixel centres sit at integers, so the image area spans [-0.5, size - 0.5]
    bad_x = ((x < -0.5) | (x > width - 0.5)).any()
    bad_y = ((y < -0.5) | (y > height - 0.5)).any()
    if bad_x or bad_y:
        raise ValueError(
            f"query positions outside the {width}x{height} frame: x must lie in "
            f"[-0.5, {width - 0.5}] and y in [-0.5, {height - 0.5}] (pixel centres at integers)"
        )


def whole_number(value: Any, name: str) -> int:
    """``value`` as an int; bools, floats and strings are refused (2.5 must not become 2)."""
    if isinstance(value, bool | np.bool_):
        raise ValueError(f"{name} must be a whole number, got {value!r}")
    try:
        return operator.index(value)
    except TypeError:
        raise ValueError(f"{name} must be a whole number, got {value!r}") from None


def grid_points(
    grid_size: int, frame: int, height: int, width: int, *, name: str = "grid_size"
) -> np.ndarray:
    """A grid_size × grid_size grid at cell centres of one frame, (N, 3) float32 (t, x, y).

    Args:
        grid_size: points per side, a whole number of at least 1.
        frame: frame index t of every query.
        height: frame height H in pixels.
        width: frame width W in pixels.
        name: how error messages call ``grid_size`` (the CLI passes ``--grid``).
    """
    grid_size = whole_number(grid_size, name)
    if grid_size < 1:
        raise ValueError(f"{name} must be at least 1, got {grid_size}")
    check_num_points(grid_size * grid_size, f"{name} {grid_size}")
    cells = np.arange(grid_size, dtype=np.float32) + np.float32(0.5)
    xs = cells * np.float32(width) / np.float32(grid_size) - np.float32(0.5)
    ys = cells * np.float32(height) / np.float32(grid_size) - np.float32(0.5)
    gy, gx = np.meshgrid(ys, xs, indexing="ij")
    return np.stack((np.full_like(gx, frame), gx, gy), axis=-1).reshape(-1, 3)
