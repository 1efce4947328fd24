"""What the evaluation calls a tracker, and the strided protocol for forward-in-time ones.

``strided`` mode scores the frames before each query too. A tracker that only follows points
forward in time is run twice: on the video, and on the time-reversed video with each query
frame t mapped to T − 1 − t; frames before a query come from the reversed pass (flipped back),
the query frame and later ones from the forward pass (TAPVID-PROTOCOL.md §1.7, TAPTRv2-SPEC.md
§4.4). The rule itself is the predictor's (`taptr.api.backward`); this module adapts numpy
trackers to it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

TrackFunction = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
"""``(video (T, H, W, 3) uint8, queries (N, 3) (t, x, y)) -> (tracks (T, N, 2), visible (T, N))``,
positions in pixels; a forward-in-time tracker."""


class Tracker(Protocol):
    """A point tracker as the evaluation sees it.

    Attributes:
        bidirectional: True when `track` also follows each point to the frames before its
            query frame; False makes ``strided`` evaluation add a time-reversed pass.
    """

    bidirectional: bool

    def track(self, video: np.ndarray, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tracks query points through a video.

        Args:
            video: (T, H, W, 3) uint8 RGB frames.
            queries: (N, 3) float (t, x, y): frame index and pixels, centres at integers.

        Returns:
            tracks (T, N, 2) float (x, y) pixels and visible (T, N) bool. Frames before a
            query's frame may hold anything unless the tracker is `bidirectional`.
        """
        ...


def query_frames(queries: np.ndarray) -> np.ndarray:
    """(N,) integer query frame of (N, 3) (t, x, y) queries, rounded as the metric does."""
    return np.round(np.asarray(queries)[:, 0]).astype(np.int64)


def track_both_ways(
    track: TrackFunction, video: np.ndarray, queries: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Forward pass plus time-reversed pass, fused at each query frame.

    The reversed pass runs with the same query set (so trackers whose points interact see
    the same points both ways); it is skipped when every query is on frame 0.

    Args:
        track: a forward-in-time tracking function (see `TrackFunction`).
        video: (T, H, W, 3) uint8 frames.
        queries: (N, 3) float (t, x, y), frame index and pixels.

    Returns:
        tracks (T, N, 2) (x, y) pixels and visible (T, N) bool on every frame.
    """
    # imported here: `taptr.eval` itself (the metric) needs numpy only, not torch
    import torch

    from taptr.api.backward import track_both_ways as fuse_both_ways

    def one_pass(pass_queries: torch.Tensor, reverse: bool) -> tuple[torch.Tensor, torch.Tensor]:
        frames = np.ascontiguousarray(video[::-1]) if reverse else video
        tracks, visible = _checked(track(frames, pass_queries.numpy()), video, queries)
        return torch.tensor(tracks), torch.tensor(visible)  # copies: outputs may be read-only

    float_queries = torch.tensor(np.asarray(queries, dtype=np.float64))
    tracks, visible = fuse_both_ways(one_pass, float_queries, video.shape[0])
    return tracks.numpy(), visible.numpy()


def run_tracker(
    tracker: Tracker, video: np.ndarray, queries: np.ndarray, query_mode: str
) -> tuple[np.ndarray, np.ndarray]:
    """Runs a tracker as ``query_mode`` needs: a reversed pass too for causal ones in strided.

    Args:
        tracker: the tracker.
        video: (T, H, W, 3) uint8 frames.
        queries: (N, 3) float (t, x, y), frame index and pixels.
        query_mode: ``"first"`` (only later frames are scored) or ``"strided"``.

    Returns:
        tracks (T, N, 2) float (x, y) pixels and visible (T, N) bool.
    """
    if query_mode == "strided" and not tracker.bidirectional:
        return track_both_ways(tracker.track, video, queries)
    return _checked(tracker.track(video, queries), video, queries)


def _checked(
    output: tuple[np.ndarray, np.ndarray], video: np.ndarray, queries: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The tracker's output as arrays, after checking their shapes."""
    tracks, visible = np.asarray(output[0], dtype=np.float64), np.asarray(output[1], dtype=bool)
    expected = (video.shape[0], queries.shape[0])
    if tracks.shape != (*expected, 2) or visible.shape != expected:
        raise ValueError(
            f"tracker returned tracks {tracks.shape} and visibility {visible.shape}; "
            f"expected (T, N, 2) = {(*expected, 2)} and (T, N) = {expected}"
        )
    return tracks, visible
