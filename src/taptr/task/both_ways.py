"""Tracking both ways in time: a forward pass, a time-reversed pass, fused at the query frames.

A forward-in-time tracker only follows a point from its query frame on. The frames before
come from a second pass over the video read backwards, in which each query frame t is
frame T − 1 − t; flipped back, that pass gives the frames before each query frame, and
the forward pass the query frame and after (TAPTRv2-SPEC.md §4.4, TAPVID-PROTOCOL.md §1.7).
The reversed pass runs with the same query set, so that points which attend to each other
see the same points both ways; it is skipped when no query has frames before it.

`Predictor.track(..., backward=True)` (through `taptr.api.backward`), the exported loop's
``track(..., backward=True)`` and the evaluation's ``strided`` protocol for forward-only
trackers all run this one rule.

Shapes: T frames, N points.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

PassFunction = Callable[[np.ndarray, bool], tuple[np.ndarray, np.ndarray]]
"""One forward-in-time pass: ``(queries (N, 3) (t, x, y), reverse) -> (tracks, values)``.

With ``reverse`` the pass reads the video backwards (its frame t is frame T − 1 − t), the
queries' t are already given in that reversed time, and its outputs are in reversed time:
tracks (T, N, 2) and per-point values (T, N) (visibility logits, or visible flags)."""


def query_frames(queries: np.ndarray) -> np.ndarray:
    """(N,) int64 query frame of (N, 3) (t, x, y) queries, rounded half to even."""
    return np.rint(np.asarray(queries)[:, 0]).astype(np.int64)


def needs_backward(queries: np.ndarray) -> bool:
    """Whether any query has frames before it (a reversed pass would change nothing else)."""
    return bool((query_frames(queries) > 0).any())


def reversed_queries(queries: np.ndarray, num_frames: int) -> np.ndarray:
    """(N, 3) (t, x, y) queries of the time-reversed video: t → T − 1 − t, x and y kept."""
    flipped = np.array(queries, copy=True)
    flipped[:, 0] = num_frames - 1 - flipped[:, 0]
    return flipped


def both_ways(
    one_pass: PassFunction, queries: np.ndarray, num_frames: int
) -> tuple[np.ndarray, np.ndarray]:
    """Forward pass plus time-reversed pass, fused at each query frame.

    Args:
        one_pass: one pass (see `PassFunction`).
        queries: (N, 3) (t, x, y): frame index and pixels.
        num_frames: T, frames in the video.

    Returns:
        tracks (T, N, 2) and values (T, N) on every frame: from the reversed pass (flipped
        back) before each point's query frame, from the forward pass on it and after.
    """
    tracks, values = one_pass(queries, False)
    if not needs_backward(queries):
        return tracks, values
    back_tracks, back_values = one_pass(reversed_queries(queries, num_frames), True)
    before = np.arange(num_frames)[:, None] < query_frames(queries)[None]  # (T, N)
    tracks = np.where(before[..., None], back_tracks[::-1], tracks)
    return tracks, np.where(before, back_values[::-1], values)
