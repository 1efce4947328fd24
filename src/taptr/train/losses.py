"""The TAPTRv2 and TAPTRv3 training losses (spec §5.3), on the full-video trajectories.

For every clip, with U the update mask (tracked frames strictly after each point's start
frame):

* visibility: sigmoid focal loss (α = 0.25, γ = 2) of the three logits against the one-hot
  of (unused, visible, occluded), summed over the channels and the U entries and divided by
  count(U) + 1. Only the last layer's term enters the total (the others are logged).
* position: L1 between predicted and true (x, y), both normalised by (W − 1, H − 1),
  summed over x, y and the entries of U whose true position lies inside the image
  (0 ≤ x, y ≤ 1, bounds inclusive; occluded points are supervised), divided by that count
  + 1. One term per decoder layer.
* updated position: the same L1 on the positions that come out of the attention-based
  position update, before each layer's position head (the paper's "supervise the position
  update" switch). One term per layer.

TAPTR (v1) divides by the counts without the + 1 (`LossWeights.count_offset` 0); an empty
count then gives 0 rather than the official 0/0 = NaN. TAPTRv3 supervises the positions of
visible entries only (`LossWeights.occluded_positions` off: the official
``not_track_invisible``), in both position terms.

Per-clip losses are averaged over the batch, so a batch of one clip gives exactly the
official values and a data-parallel run averages like one process on the combined batch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from taptr.model.trajectory import TrackOutput


@dataclass(frozen=True)
class LossWeights:
    """How the terms are combined (defaults: the official weight dict).

    Attributes:
        visibility: weight of the last layer's focal visibility term.
        position: weight of every layer's L1 position term.
        supervise_updated_positions: also add every layer's L1 term on the position-update
            outputs, with weight ``position`` (Table 3 of the paper ablates this).
        focal_alpha: α of the focal loss (weight of positive targets).
        focal_gamma: γ of the focal loss.
        count_offset: added to the entry counts that normalise each term (1 in TAPTRv2,
            0 in TAPTR v1).
        occluded_positions: the position terms also count entries where the point is
            occluded (TAPTRv2); off, only visible ones (TAPTRv3).
    """

    visibility: float = 1.0
    position: float = 5.0
    supervise_updated_positions: bool = True
    focal_alpha: float = 0.25
    focal_gamma: float = 2.0
    count_offset: float = 1.0
    occluded_positions: bool = True


class Targets(NamedTuple):
    """Ground truth of a batch of clips, in model units.

    Attributes:
        positions: (B, T, N, 2) true (x, y) normalised by (W − 1, H − 1); may lie outside
            [0, 1] where the point left the image.
        visible: (B, T, N) bool true visibility.
        start_frames: (B, N) int64 query frame of each point.
    """

    positions: Tensor
    visible: Tensor
    start_frames: Tensor


class LossOutput(NamedTuple):
    """The weighted total and every term.

    Attributes:
        total: scalar to back-propagate.
        terms: ``visibility_{l}``, ``position_{l}`` and (with the position update)
            ``updated_position_{l}`` for every layer l, unweighted and detached.
    """

    total: Tensor
    terms: dict[str, Tensor]


def update_mask(start_frames: Tensor, num_frames: int) -> Tensor:
    """U: frames strictly after each point's start, (B, N) → (B, T, N) bool."""
    frames = torch.arange(num_frames, device=start_frames.device)
    return frames[None, :, None] > start_frames[:, None, :]


def inside_image(positions: Tensor) -> Tensor:
    """Whether normalised (x, y) lies in [0, 1]² (inclusive), (..., 2) → (...)."""
    return ((positions >= 0) & (positions <= 1)).all(dim=-1)


def _normaliser(mask: Tensor, offset: float, dtype: torch.dtype) -> Tensor:
    """Per-clip count of masked entries plus ``offset``, at least 1 when the offset is 0."""
    count = mask.sum((1, 2)).to(dtype) + offset
    return count if offset else count.clamp(min=1)


def focal_visibility_loss(
    logits: Tensor,
    visible: Tensor,
    mask: Tensor,
    alpha: float = 0.25,
    gamma: float = 2.0,
    count_offset: float = 1.0,
) -> Tensor:
    """Per-clip sigmoid focal loss of the three visibility logits.

    Args:
        logits: (B, T, N, 3) channel 1 = visible, channel 2 = occluded, channel 0 unused
            (its target is always 0).
        visible: (B, T, N) bool ground truth.
        mask: (B, T, N) bool entries that count.
        alpha: weight of positive targets (1 − alpha for negatives).
        gamma: focusing exponent.
        count_offset: added to the count of masked entries that divides the sum.

    Returns:
        (B,) summed over channels and masked entries, divided by count + count_offset.
    """
    target = F.one_hot(torch.where(visible, 1, 2), 3).to(logits.dtype)
    probability = logits.sigmoid()
    cross_entropy = F.binary_cross_entropy_with_logits(logits, target, reduction="none")
    p_true = probability * target + (1 - probability) * (1 - target)
    weight = alpha * target + (1 - alpha) * (1 - target)
    loss = weight * cross_entropy * (1 - p_true) ** gamma  # (B, T, N, 3)
    masked = loss.sum(-1) * mask.to(loss.dtype)
    return masked.sum((1, 2)) / _normaliser(mask, count_offset, loss.dtype)


def position_loss(
    predicted: Tensor, target: Tensor, mask: Tensor, count_offset: float = 1.0
) -> Tensor:
    """Per-clip L1 of (x, y), summed over masked entries and divided by count + offset.

    Args:
        predicted: (B, T, N, 2) normalised positions.
        target: (B, T, N, 2) normalised true positions.
        mask: (B, T, N) bool entries that count.
        count_offset: added to the count of masked entries that divides the sum.

    Returns:
        (B,).
    """
    # torch.where keeps NaN/inf of unused entries (e.g. far outside the image) out of the sum
    error = torch.where(mask[..., None], (predicted - target).abs(), 0).sum(-1)
    return error.sum((1, 2)) / _normaliser(mask, count_offset, predicted.dtype)


def tracking_loss(output: TrackOutput, targets: Targets, weights: LossWeights) -> LossOutput:
    """Every loss term of a training forward and their weighted sum.

    Args:
        output: the tracker's full-video output in training mode (position logits and
            visibility logits of every layer).
        targets: the ground truth.
        weights: term weights and the focal parameters.
    """
    layers, _, num_frames = output.layer_positions.shape[:3]
    updates = update_mask(targets.start_frames, num_frames)
    located = updates & inside_image(targets.positions)
    if not weights.occluded_positions:
        located = located & targets.visible
    gt = targets.positions.to(output.layer_positions.dtype)

    terms: dict[str, Tensor] = {}
    total = output.layer_positions.new_zeros(())
    for layer in range(layers):
        visibility = focal_visibility_loss(
            output.layer_visibility_logits[layer],
            targets.visible,
            updates,
            weights.focal_alpha,
            weights.focal_gamma,
            weights.count_offset,
        ).mean()
        position = position_loss(
            output.layer_positions[layer, ..., :2].sigmoid(), gt, located, weights.count_offset
        ).mean()
        terms[f"visibility_{layer}"] = visibility
        terms[f"position_{layer}"] = position
        total = total + weights.position * position
        if layer == layers - 1:
            total = total + weights.visibility * visibility
        if output.layer_updated_positions is not None:
            updated = position_loss(
                output.layer_updated_positions[layer, ..., :2].sigmoid(),
                gt,
                located,
                weights.count_offset,
            ).mean()
            terms[f"updated_position_{layer}"] = updated
            if weights.supervise_updated_positions:
                total = total + weights.position * updated
    return LossOutput(total, {name: value.detach() for name, value in terms.items()})
