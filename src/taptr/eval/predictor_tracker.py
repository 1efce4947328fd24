"""taptr's own tracker for the ``standard`` protocol: `taptr.Predictor` as an evaluation tracker.

The predictor is evaluated as users get it: it resizes the 256 × 256 frames to the model's
input size itself, and in ``strided`` mode its own time-reversed pass (``backward=True``)
tracks the frames before each query.
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
    """

    def __init__(self, predictor: Predictor, *, backward: bool) -> None:
        self.predictor = predictor
        self.bidirectional = backward

    @classmethod
    def from_pretrained(
        cls,
        name_or_path: str | os.PathLike[str] | None,
        *,
        backward: bool,
        device: str | torch.device | None = None,
    ) -> PredictorTracker:
        """A tracker for a checkpoint file or model name (None: the bundled default)."""
        return cls(Predictor.from_pretrained(name_or_path, device=device), backward=backward)

    def track(self, video: np.ndarray, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tracks query points through a video.

        Args:
            video: (T, H, W, 3) uint8 RGB frames.
            queries: (N, 3) float (t, x, y), frame index and pixels (centres at integers).

        Returns:
            tracks (T, N, 2) float32 (x, y) pixels and visible (T, N) bool.
        """
        result = self.predictor.track(video, queries=queries, backward=self.bidirectional)
        return result.tracks[0].cpu().numpy(), result.visibility[0].cpu().numpy()
