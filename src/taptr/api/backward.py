"""Tracking both ways in time with torch passes: `taptr.task.both_ways`'s rule on tensors.

`Predictor.track(..., backward=True)` and the evaluation's ``strided`` protocol for
forward-only trackers (`taptr.eval.trackers.track_both_ways`) hand their passes here; the
fusion itself (which frames come from which pass) is written once, in numpy, in
`taptr.task.both_ways`, and the tensors cross over without copies (they are on the host).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from taptr.task import both_ways as rule

PassFunction = Callable[[Tensor, bool], tuple[Tensor, Tensor]]
"""One forward-in-time pass (`taptr.task.both_ways.PassFunction`) on host tensors."""


def query_frames(queries: Tensor) -> Tensor:
    """(N,) int64 query frame of (N, 3) (t, x, y) queries, rounded half to even (as numpy)."""
    return torch.from_numpy(rule.query_frames(queries.detach().cpu().numpy()))


def needs_backward(queries: Tensor) -> bool:
    """Whether any query has frames before it (a reversed pass would change nothing else)."""
    return rule.needs_backward(queries.detach().cpu().numpy())


def reversed_queries(queries: Tensor, num_frames: int) -> Tensor:
    """(N, 3) (t, x, y) queries of the time-reversed video: t → T − 1 − t, x and y kept."""
    return torch.from_numpy(rule.reversed_queries(queries.detach().cpu().numpy(), num_frames))


def track_both_ways(track: PassFunction, queries: Tensor, num_frames: int) -> tuple[Tensor, Tensor]:
    """Forward pass plus time-reversed pass, fused at each query frame (`taptr.task.both_ways`).

    Args:
        track: one pass (see `PassFunction`); its outputs on the host.
        queries: (N, 3) (t, x, y): frame index and pixels, on the host.
        num_frames: T, frames in the video.

    Returns:
        tracks (T, N, 2) and values (T, N) on every frame.
    """

    def one_pass(pass_queries: np.ndarray, reverse: bool) -> tuple[np.ndarray, np.ndarray]:
        tracks, values = track(torch.from_numpy(pass_queries), reverse)
        return tracks.numpy(), values.numpy()

    tracks, values = rule.both_ways(one_pass, queries.numpy(), num_frames)
    return torch.from_numpy(np.ascontiguousarray(tracks)), torch.from_numpy(
        np.ascontiguousarray(values)
    )
