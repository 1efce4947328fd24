"""Tracking both ways in time: a forward pass, a time-reversed pass, fused at the query frames.

A forward-in-time tracker only follows a point to its query frame and later ones. The frames
before come from a second pass over the video read backwards, in which each query frame t is
frame T − 1 − t; flipped back, that pass gives the frames before each query frame, and the
forward pass the query frame and after (TAPTRv2-SPEC.md §4.4, TAPVID-PROTOCOL.md §1.7).

`Predictor.track(..., backward=True)` and the evaluation's ``strided`` protocol for
forward-only trackers (`taptr.eval.trackers.track_both_ways`) both run this one rule.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

PassFunction = Callable[[Tensor, bool], tuple[Tensor, Tensor]]
"""One forward-in-time pass: ``(queries (N, 3) (t, x, y), reverse) -> (tracks, values)``.

With ``reverse`` the pass reads the video backwards (its frame t is frame T − 1 − t), the
queries' t are already given in that reversed time, and its outputs are in reversed time:
tracks (T, N, 2) and per-point values (T, N) (visibility logits, or visible flags)."""


def query_frames(queries: Tensor) -> Tensor:
    """(N,) int64 query frame of (N, 3) (t, x, y) queries, rounded half to even (as numpy)."""
    return queries[:, 0].round().long()


def needs_backward(queries: Tensor) -> bool:
    """Whether any query has frames before it (a reversed pass would change nothing else)."""
    return bool((query_frames(queries) > 0).any())


def reversed_queries(queries: Tensor, num_frames: int) -> Tensor:
    """(N, 3) (t, x, y) queries of the time-reversed video: t → T − 1 − t, x and y kept."""
    flipped = queries.clone()
    flipped[:, 0] = num_frames - 1 - queries[:, 0]
    return flipped


def track_both_ways(track: PassFunction, queries: Tensor, num_frames: int) -> tuple[Tensor, Tensor]:
    """Forward pass plus time-reversed pass, fused at each query frame.

    The reversed pass runs with the same query set (points that attend to each other see
    the same points both ways); it is skipped when no query has frames before it.

    Args:
        track: one pass (see `PassFunction`).
        queries: (N, 3) (t, x, y): frame index and pixels.
        num_frames: T, frames in the video.

    Returns:
        tracks (T, N, 2) and values (T, N) on every frame: from the reversed pass (flipped
        back) before each point's query frame, from the forward pass on it and after.
    """
    tracks, values = track(queries, False)
    if not needs_backward(queries):
        return tracks, values
    back_tracks, back_values = track(reversed_queries(queries, num_frames), True)
    before = torch.arange(num_frames)[:, None] < query_frames(queries)[None]  # (T, N)
    tracks = torch.where(before[..., None], back_tracks.flip(0), tracks)
    values = torch.where(before, back_values.flip(0), values)
    return tracks, values
