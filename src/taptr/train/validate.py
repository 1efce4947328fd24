"""Held-out evaluation during training, scored with the TAP-Vid metric.

Each held-out clip is resized to the model input, keeps up to N points visible on its first
or middle frame, queried at their first visible frame, and is tracked by the model in
evaluation mode. It reports the training loss terms, the mean position error on visible
frames after each query (in pixels of a 256 × 256 frame, TAP-Vid's scale), and the TAP-Vid
``first``-mode metrics of `taptr.eval.metrics` (``average_jaccard``,
``average_pts_within_thresh``, ``occlusion_accuracy``), averaged over clips as the
benchmark does.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable

import torch

from taptr.data.sampling import TrainingClip, collate
from taptr.eval.metrics import mean_over_videos, tapvid_metrics
from taptr.geometry import normalized_to_pixels
from taptr.model.taptr import TAPTR
from taptr.train.forward import TrainingForward, batch_targets
from taptr.train.losses import LossWeights, tracking_loss, update_mask
from taptr.train.precision import autocast

METRIC_SCALE = 256


@torch.no_grad()
def evaluate(
    model: TAPTR,
    clips: Iterable[TrainingClip],
    weights: LossWeights,
    device: torch.device,
    precision: str = "fp32",
) -> dict[str, float]:
    """Loss terms and tracking metrics averaged over ``clips`` (one clip at a time).

    Returns:
        ``loss``, every loss term, ``position_error``, ``delta_avg`` and
        ``occlusion_accuracy``.
    """
    was_training = model.training
    model.eval()
    forward = TrainingForward(model)
    sums: dict[str, float] = defaultdict(float)
    clip_count, errors, visible_count = 0, 0.0, 0
    per_clip: list[dict[str, float]] = []
    try:
        for clip in clips:
            batch = collate([clip]).to(device)
            with autocast(precision, device):
                output = forward(*batch)
            loss = tracking_loss(output, batch_targets(batch), weights)
            sums["loss"] += loss.total.item()
            for name, value in loss.terms.items():
                sums[name] += value.item()
            clip_count += 1

            after = update_mask(batch.start_frames, batch.video.shape[1])  # (1, T, N)
            seen = after & batch.visible
            predicted = normalized_to_pixels(output.positions.float(), METRIC_SCALE, METRIC_SCALE)
            truth = normalized_to_pixels(batch.positions.float(), METRIC_SCALE, METRIC_SCALE)
            errors += (predicted - truth).norm(dim=-1)[seen].sum().item()
            visible_count += int(seen.sum())
            per_clip.append(
                _tapvid_first(
                    batch.start_frames[0],
                    truth[0],
                    batch.visible[0],
                    predicted[0],
                    output.visibility_logits[0, ..., 1] > 0,
                )
            )
    finally:
        model.train(was_training)
    metrics = {name: total / max(clip_count, 1) for name, total in sums.items()}
    metrics["position_error"] = errors / max(visible_count, 1)
    metrics.update(mean_over_videos(per_clip))
    return metrics


def _tapvid_first(
    starts: torch.Tensor,
    truth: torch.Tensor,
    visible: torch.Tensor,
    predicted: torch.Tensor,
    predicted_visible: torch.Tensor,
) -> dict[str, float]:
    """TAP-Vid ``first``-mode metrics of one clip, positions in 256-frame pixels.

    Args:
        starts: (N,) query frames.
        truth: (T, N, 2) ground-truth (x, y).
        visible: (T, N) ground-truth visibility.
        predicted: (T, N, 2) predicted (x, y).
        predicted_visible: (T, N) predicted visibility.
    """
    points = torch.arange(starts.shape[0], device=starts.device)
    queries = torch.cat((starts[:, None].float(), truth[starts, points]), dim=-1)  # (N, 3)
    return tapvid_metrics(
        queries.cpu().numpy(),
        truth.cpu().numpy(),
        visible.cpu().numpy(),
        predicted.cpu().numpy(),
        predicted_visible.cpu().numpy(),
        "first",
    )
