"""The model-level forward in the official conventions, for checkpoint equivalence checks.

Inputs and outputs follow the authors' code: an already preprocessed video, positions
normalised by (W − 1, H − 1), three visibility logits per point and frame (channel 1 =
visible), and every decoder layer's trajectories. Tracking users want `taptr.Predictor`.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from taptr.model.taptr import TAPTR
from taptr.model.trajectory import QuerySet
from taptr.runtime.engines import run_tracker
from taptr.runtime.frames import EncodedFrames


def _check_inputs(
    video: Tensor, query_frames: Tensor, query_xy: Tensor, query_labels: Tensor | None
) -> None:
    if video.dim() != 5 or video.shape[0] != 1 or video.shape[2] != 3:
        raise ValueError(f"video must be (1, T, 3, H, W), got {tuple(video.shape)}")
    if not video.is_floating_point():
        raise ValueError(f"video must be a preprocessed float tensor, got {video.dtype}")
    num_frames, points = video.shape[1], query_frames.shape[0]
    if query_frames.dim() != 1 or query_xy.shape != (points, 2):
        raise ValueError(
            f"query_frames must be (N,) and query_xy (N, 2); got {tuple(query_frames.shape)} "
            f"and {tuple(query_xy.shape)}"
        )
    if points and (int(query_frames.min()) < 0 or int(query_frames.max()) >= num_frames):
        raise ValueError(f"query_frames must lie in [0, {num_frames - 1}]")
    if not bool(torch.isfinite(query_xy).all()):
        raise ValueError("query_xy contains NaN or infinite values")
    if query_labels is not None and (
        query_labels.shape != (points,)
        or not bool(((query_labels == 1) | (query_labels == 2)).all())
    ):
        raise ValueError("query_labels must be (N,) with values 1 (visible) or 2 (occluded)")


@torch.no_grad()
def official_forward(
    model: TAPTR,
    video: Tensor,
    query_frames: Tensor,
    query_xy: Tensor,
    query_labels: Tensor | None = None,
    *,
    history_frames: int | None = None,
) -> dict[str, Any]:
    """Runs the model exactly as the official code does at evaluation (no query padding).

    TAPTR v1 and TAPTRv2 run their sliding windows; TAPTRv3 runs frame by frame as the
    official streaming evaluation (``--streaming``) does.

    Args:
        model: a TAPTR model (switched to eval mode for the call).
        video: (1, T, 3, H, W) float, already resized and ImageNet-normalised.
        query_frames: (N,) int start frame of each point.
        query_xy: (N, 2) start (x, y) normalised by (W − 1, H − 1).
        query_labels: (N,) optional start labels, 1 visible (default) or 2 occluded; they
            only set the logits of frames the model never writes (TAPTRv3 with visibility
            weights ignores them, as the official code does).
        history_frames: TAPTRv3 only: the most frames held per point, the current one
            included (the official ``streaming_limited_size_of_placeholder``; 0: all).
            Default: the model's.

    Returns:
        ``positions`` (T, N, 2) normalised and ``visibility_logits`` (T, N, 3) of the last
        layer, and ``layers``: one dict per decoder layer with the same two keys plus
        ``updated_positions`` (T, N, 2), the position-update output (None without it).
    """
    _check_inputs(video, query_frames, query_xy, query_labels)
    was_training = model.training
    model.eval()
    try:
        device = video.device
        visible = (
            torch.ones_like(query_frames, dtype=torch.bool)
            if query_labels is None
            else query_labels == 1
        )
        queries = QuerySet(
            query_frames.to(device=device, dtype=torch.long)[None],
            query_xy.to(device=device, dtype=video.dtype)[None],
            visible.to(device)[None],
        )
        output = run_tracker(
            model,
            queries,
            video.shape[1],
            EncodedFrames(model, video),
            video.dtype,
            history_frames=history_frames,
        )
    finally:
        model.train(was_training)
    layers = []
    for index in range(model.num_layers):
        updated = output.layer_updated_positions
        layers.append(
            {
                "positions": output.layer_positions[index, 0, ..., :2].sigmoid(),
                "visibility_logits": output.layer_visibility_logits[index, 0],
                "updated_positions": None
                if updated is None
                else updated[index, 0, ..., :2].sigmoid(),
            }
        )
    return {
        "positions": output.positions[0],
        "visibility_logits": output.visibility_logits[0],
        "layers": layers,
    }
