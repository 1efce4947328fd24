"""Support points: the static extra queries TAPTRv3's evaluation adds around the user's.

TAPTRv3's points attend to each other in every decoder layer, as TAPTRv2's do, but its
evaluation surrounds the real points with a fixed pattern instead of 800 random ones
(TAPTRv3-DELTA.md §5.2, 'local_and_grid'), in 256 × 256 pixels where a normalised
coordinate is x / 255:

1. 63 local points per real point: its query position plus the offsets of an 8 × 8 grid
   spanning ±24 px (``linspace(−24, 24, 8)``, x fastest) without entry 32, which the
   official code removes as if it were the centre: (−24, +3.43). Each starts on its
   parent's query frame. They may lie outside the frame.
2. 36 grid points on ``linspace(16, 239, 6)``², x fastest, each starting on a frame r
   drawn from [0, 12) (``randint(0, 12, 36)``) by a numpy generator seeded with 42: the
   official evaluation draws them from numpy's global generator, seeded once with 42, one
   draw per video in dataset order (`taptr.eval` replays that order); a predictor draws
   the first draw for every video.

``grid`` adds the grid points only: 36 points, whatever the number of queries, for dense
queries that support each other.
"""

from __future__ import annotations

import numpy as np
import torch

from taptr.model.trajectory import QuerySet

LOCAL_SPAN = 24.0
"""Half the side of the local pattern, in 256 × 256 pixels."""
LOCAL_SIDE = 8
GRID_SIDE = 6
GRID_POINTS = GRID_SIDE * GRID_SIDE
GRID_MARGIN = 16
GRID_SEED = 42
PREFIX_FRAMES = 12
"""Grid points start on a frame drawn from [0, 12)."""
EVAL_SCALE = 255.0
"""A normalised coordinate is a 256 × 256 pixel divided by 255."""


def local_offsets() -> np.ndarray:
    """(63, 2) local (dx, dy) in 256 × 256 pixels, x fastest, entry 32 removed."""
    line = np.linspace(-LOCAL_SPAN, LOCAL_SPAN, LOCAL_SIDE)
    xs, ys = np.meshgrid(line, line)
    grid = np.stack((xs.ravel(), ys.ravel()), axis=-1)  # (64, 2)
    return np.delete(grid, LOCAL_SIDE * LOCAL_SIDE // 2, axis=0)


LOCAL_OFFSETS = local_offsets()
"""(63, 2) the local pattern, in 256 × 256 pixels."""


def grid_positions() -> np.ndarray:
    """(36, 2) grid (x, y) in 256 × 256 pixels, x fastest."""
    line = np.linspace(GRID_MARGIN, 256 - 1 - GRID_MARGIN, GRID_SIDE)
    xs, ys = np.meshgrid(line, line)
    return np.stack((xs.ravel(), ys.ravel()), axis=-1)


def grid_start_frames(rng: np.random.RandomState) -> np.ndarray:
    """(36,) the grid points' start frames: one official draw.

    A video shorter than a draw never starts that point, which then influences nothing
    (the official code requires 12 frames), so streams of unknown length agree with it.
    """
    return rng.randint(0, PREFIX_FRAMES, GRID_POINTS).astype(np.int64)


def with_support(queries: QuerySet, scheme: str, grid_starts: np.ndarray | None = None) -> QuerySet:
    """The query set with support points after the real ones.

    Args:
        queries: the real points, (B, N, ·) in model units.
        scheme: ``"local_and_grid"`` or ``"grid"``.
        grid_starts: (36,) the grid points' start frames; default the first draw of a
            generator seeded with 42.

    Returns:
        (B, N + K, ·) queries: local points in real-point order, then the grid. All are
        static and start visible.
    """
    if scheme not in ("local_and_grid", "grid"):
        raise ValueError(f"unknown support scheme {scheme!r}; use 'local_and_grid' or 'grid'")
    if grid_starts is None:
        grid_starts = grid_start_frames(np.random.RandomState(GRID_SEED))
    device, dtype = queries.positions.device, queries.positions.dtype
    batch = queries.start_frames.shape[0]
    grid = torch.from_numpy(grid_positions() / EVAL_SCALE).to(device, dtype)
    parts = [queries]
    if scheme == "local_and_grid":
        parts.append(local_points(queries))
    parts.append(
        QuerySet(
            torch.from_numpy(grid_starts).to(device).expand(batch, -1),
            grid.expand(batch, -1, -1),
            torch.ones(batch, len(grid), dtype=torch.bool, device=device),
        )
    )
    return QuerySet(*(torch.cat(column, dim=1) for column in zip(*parts, strict=True)))


def local_points(queries: QuerySet) -> QuerySet:
    """The 63 local points of each query, (B, 63·N, ·), in query order; static, visible."""
    offsets = torch.from_numpy(LOCAL_OFFSETS / EVAL_SCALE)
    offsets = offsets.to(queries.positions.device, queries.positions.dtype)  # (63, 2)
    positions = (queries.positions[:, :, None] + offsets).flatten(1, 2)
    return QuerySet(
        queries.start_frames.repeat_interleave(len(offsets), dim=1),
        positions,
        torch.ones(positions.shape[:2], dtype=torch.bool, device=positions.device),
    )
