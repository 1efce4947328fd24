"""The training forward as one module call, and the queries and targets of a batch.

`TrainingForward` wraps the model so that encoding and the window loop run inside a single
``forward``: DistributedDataParallel only synchronises gradients of work done through the
wrapped module's ``forward``.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from taptr.data.sampling import ClipBatch
from taptr.model.taptr import TAPTR, normalize_frames
from taptr.model.trajectory import QuerySet, TrackOutput
from taptr.runtime.engines import run_tracker
from taptr.runtime.frames import PrecomputedFrames
from taptr.train.losses import Targets


def batch_queries(batch: ClipBatch) -> QuerySet:
    """Each point's true position and visibility at its start frame, as model queries."""
    index = batch.start_frames[:, None, :]  # (B, 1, N)
    positions = batch.positions.gather(1, index[..., None].expand(-1, -1, -1, 2))[:, 0]
    visible = batch.visible.gather(1, index)[:, 0]
    return QuerySet(batch.start_frames, positions, visible)


def batch_targets(batch: ClipBatch) -> Targets:
    """The ground truth the losses compare with."""
    return Targets(batch.positions, batch.visible, batch.start_frames)


class TrainingForward(nn.Module):
    """Encodes a batch of clips and tracks its queries through every window (or frame).

    Shape:
        video (B, T, 3, H, W) uint8 RGB; positions (B, T, N, 2) normalised (x, y);
        visible (B, T, N) bool; start_frames (B, N) → `TrackOutput` with per-layer
        trajectories over all T frames.
    """

    def __init__(self, model: TAPTR) -> None:
        super().__init__()
        self.model = model

    def forward(
        self, video: Tensor, positions: Tensor, visible: Tensor, start_frames: Tensor
    ) -> TrackOutput:
        """Runs the model on the clips (the tensors of a `ClipBatch`)."""
        frames = normalize_frames(video.float() / 255)
        queries = batch_queries(ClipBatch(video, positions, visible, start_frames))
        features = self.model.encode(frames)
        return run_tracker(
            self.model, queries, video.shape[1], PrecomputedFrames(features), torch.float32
        )
