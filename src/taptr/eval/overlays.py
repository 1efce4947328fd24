"""Overlay videos of the worst-scored videos: ground truth on the left, prediction on the right.

Only the k worst predictions seen so far are kept (tracks, not frames); the video itself is
loaded again when its overlay is drawn, so memory stays at one decoded video.
"""

from __future__ import annotations

import heapq
import math
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from taptr.data.tapvid import PendingVideo
from taptr.eval.protocols import EvalProtocol, Prediction, VideoResult
from taptr.eval.trackers import query_frames

OVERLAY_FPS = 10.0


class Candidate(NamedTuple):
    """A video that may be among the worst, with what is needed to draw it again.

    Attributes:
        result: its scores.
        pending: its loader.
        prediction: its predicted tracks and ground truth.
    """

    result: VideoResult
    pending: PendingVideo
    prediction: Prediction


class WorstVideos:
    """Keeps the ``count`` videos of lowest average Jaccard (videos without a score are skipped).

    Args:
        count: how many to keep.
    """

    def __init__(self, count: int) -> None:
        self.count = count
        self._heap: list[tuple[float, int, Candidate]] = []

    def offer(self, candidate: Candidate) -> None:
        """Keeps ``candidate`` if it is among the worst so far."""
        score = candidate.result.metrics.get("average_jaccard", math.nan)
        if self.count <= 0 or not math.isfinite(score):
            return
        # heapq is a min-heap: store −AJ so the best of the kept ones is popped first
        item = (-score, -candidate.result.index, candidate)
        if len(self._heap) < self.count:
            heapq.heappush(self._heap, item)
        elif item[:2] > self._heap[0][:2]:
            heapq.heapreplace(self._heap, item)

    def candidates(self) -> list[Candidate]:
        """The kept videos, worst first."""
        return [item[2] for item in sorted(self._heap, key=lambda i: i[:2], reverse=True)]


def worst_indices(results: list[VideoResult], count: int) -> list[int]:
    """Dataset indices of the ``count`` lowest average-Jaccard videos, worst first."""
    scored = [r for r in results if math.isfinite(r.metrics.get("average_jaccard", math.nan))]
    scored.sort(key=lambda r: (r.metrics["average_jaccard"], r.index))
    return [r.index for r in scored[:count]]


def write_overlay(
    path: str | os.PathLike[str],
    protocol: EvalProtocol,
    candidate: Candidate,
    query_mode: str,
) -> Path:
    """Draws ground truth | prediction side by side on the 256 × 256 clip and writes an mp4.

    Args:
        path: output ``.mp4`` file.
        protocol: the protocol the video was scored with (it prepares the clip again).
        candidate: the video and its prediction.
        query_mode: in ``first`` mode points are drawn from their query frame on, in
            ``strided`` mode on every frame.
    """
    from taptr.io.video import write_video
    from taptr.viz.draw import draw_tracks, point_colors

    video = protocol.prepare(candidate.pending.load()).video
    prediction = candidate.prediction
    points = prediction.points
    starts = query_frames(points.queries) if query_mode == "first" else None
    colors = point_colors(points.queries[:, 1:])  # one colour per point on both sides
    truth = draw_tracks(video, points.tracks, points.visible, query_frames=starts, colors=colors)
    predicted = draw_tracks(
        video, prediction.tracks, prediction.visible, query_frames=starts, colors=colors
    )
    return write_video(path, np.concatenate([truth, predicted], axis=2), OVERLAY_FPS)
