"""taptr's own tracker for the ``standard`` protocol: `taptr.Predictor` as an evaluation tracker.

The predictor is evaluated as users get it: it resizes the 256 × 256 frames to the model's
input size itself, adds the model's context points to each video's queries, and in
``strided`` mode its own time-reversed pass (``backward=True``) tracks the frames before
each query.
"""

from __future__ import annotations

import os

import numpy as np
import torch

from taptr.api.predictor import Predictor


class PredictorTracker:
    """Adapts `taptr.Predictor` to the evaluation's `Tracker` protocol.

    Args:
        predictor: the predictor.
        backward: also track the frames before each query (needed by ``strided`` mode only).
        points_per_call: track the queries in groups of this many, one predictor call each,
            as a user clicking a few points would (None: all at once).
    """

    def __init__(
        self, predictor: Predictor, *, backward: bool, points_per_call: int | None = None
    ) -> None:
        if points_per_call is not None and points_per_call < 1:
            raise ValueError(f"points_per_call must be at least 1, got {points_per_call}")
        self.predictor = predictor
        self.bidirectional = backward
        self.points_per_call = points_per_call

    @classmethod
    def from_pretrained(
        cls,
        name_or_path: str | os.PathLike[str] | None,
        *,
        backward: bool,
        device: str | torch.device | None = None,
        context_points: int | None = None,
        support_points: str | None = None,
        points_per_call: int | None = None,
        autocast: torch.dtype | None = None,
    ) -> PredictorTracker:
        """A tracker for a checkpoint file or model name (None: the default model).

        ``context_points``, ``support_points`` and ``autocast`` as in `Predictor` (None:
        the model's own count and scheme; no autocast).
        """
        predictor = Predictor.from_pretrained(
            name_or_path,
            device=device,
            context_points=context_points,
            support_points=support_points,
            autocast=autocast,
        )
        return cls(predictor, backward=backward, points_per_call=points_per_call)

    def track(self, video: np.ndarray, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tracks query points through a video.

        Args:
            video: (T, H, W, 3) uint8 RGB frames.
            queries: (N, 3) float (t, x, y), frame index and pixels (centres at integers).

        Returns:
            tracks (T, N, 2) float32 (x, y) pixels and visible (T, N) bool.
        """
        size = self.points_per_call or max(len(queries), 1)
        tracks, visible = [], []
        for first in range(0, max(len(queries), 1), size):
            result = self.predictor.track(
                video, queries=queries[first : first + size], backward=self.bidirectional
            )
            tracks.append(result.tracks[0].cpu().numpy())
            visible.append(result.visibility[0].cpu().numpy())
        return np.concatenate(tracks, axis=1), np.concatenate(visible, axis=1)
