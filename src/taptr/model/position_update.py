"""The Attention-based Position Update (APU), step by step, in the paper's order.

Each TAPTRv2 decoder layer's cross-attention samples M·L·P locations around a point at
offsets o_s (feature pixels of level l). In words, for one point on one frame:

1. Weights. With the disentangler (the paper), an MLP maps the cross-attention's
   pre-softmax logits to new ones and w = softmax over all M·L·P samples, so that the
   position and the content attention are decoupled; without it, each head's own content
   weights (softmax over its L·P samples) are used (`PositionUpdate`).
2. Displacement. Δ = Σ_s w_s · o_s / (H_l, W_l), the weighted mean offset in normalised
   image units (averaged over heads without the disentangler) (`PositionUpdate`).
3. Move. p' = clamp(p + Δ, 0, 1) where the point is being updated (after its start frame),
   p' = p elsewhere; the displacement kept for later is d = update · (clamp(p + Δ) − p)
   (`move_reference`). The layer then re-embeds p' as the query position for its temporal
   and point attention.
4. Fusion. The features the position and visibility heads read are
   F([content, sine(d)]), the layer's content fused with the displacement's sine
   embedding (`fuse_displacement`).
5. Outputs. The position head adds δ to p' in logit space: the next layer's reference is
   σ(δ + σ⁻¹(p')), detached, and the reported positions are δ + σ⁻¹(σ(σ⁻¹(p'))), one more
   sigmoid round trip than the reference, as in the official code (`refine_updated`).

Nothing is detached inside the update itself: gradients reach the offsets and the logits.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor, nn

from taptr.geometry import clamp_to_unit, inverse_sigmoid
from taptr.model.execution import Execution
from taptr.model.layers import MLP
from taptr.model.position_encoding import point_embedding


def normalize_offsets(offsets: Tensor, spatial_shapes: list[tuple[int, int]]) -> Tensor:
    """Divides offsets (x, y) of level l by (H_l, W_l).

    The official code divides x by the height and y by the width (the opposite of the
    sampling step); identical for square maps, kept for checkpoint fidelity.

    Args:
        offsets: (..., L, P, 2) raw offsets in feature pixels.
        spatial_shapes: (H_l, W_l) per level.
    """
    sizes = offsets.new_tensor([[h, w] for h, w in spatial_shapes])  # (L, 2)
    return offsets / sizes[:, None, :]


class PositionUpdate(nn.Module):
    """Steps 1 and 2: the displacement Δ from cross-attention logits and offsets.

    Attributes:
        disentangler: the MLP from content-attention logits to position-update logits, or
            None to reuse the content attention weights.

    Shape:
        logits (B, Q, M, L, P), offsets (B, Q, M, L, P, 2) → displacement (B, Q, 2).
    """

    def __init__(self, num_samples: int, hidden_dim: int, disentangler: bool) -> None:
        """Creates the update.

        Args:
            num_samples: M·L·P sampled locations per query.
            hidden_dim: width of the disentangler MLP (d_model).
            disentangler: learn separate position weights (paper) or reuse the content
                attention weights.
        """
        super().__init__()
        self.disentangler = MLP(num_samples, hidden_dim, num_samples, 3) if disentangler else None

    def forward(
        self,
        logits: Tensor,
        offsets: Tensor,
        spatial_shapes: list[tuple[int, int]],
        execution: Execution | None = None,
    ) -> Tensor:
        """Returns Δ (x, y) in normalised image units; nothing is detached.

        Args:
            logits: (B, Q, M, L, P) pre-softmax cross-attention logits.
            offsets: (B, Q, M, L, P, 2) sampling offsets (x, y) in feature pixels.
            spatial_shapes: (H_l, W_l) per level.
            execution: how the disentangler MLP runs (`taptr.model.layers.MLP`).
        """
        moves = normalize_offsets(offsets, spatial_shapes)  # (B, Q, M, L, P, 2)
        if self.disentangler is not None:
            flat_logits = logits.flatten(2)  # (B, Q, M·L·P), order (head, level, point)
            weights = self.disentangler(flat_logits, execution).softmax(-1)
            return (weights.unsqueeze(-1) * moves.flatten(2, 4)).sum(2)
        weights = logits.flatten(3).softmax(-1)  # (B, Q, M, L·P), per-head content weights
        per_head = (weights.unsqueeze(-1) * moves.flatten(3, 4)).sum(3)  # (B, Q, M, 2)
        return per_head.mean(2)


class MovedReference(NamedTuple):
    """Step 3's result.

    Attributes:
        reference: (B, W_t, N, 4) the moved reference p' (x, y, w, h) in [0, 1].
        displacement: (B, W_t, N, 2) the masked displacement d, zero where not updated.
    """

    reference: Tensor
    displacement: Tensor


def move_reference(reference: Tensor, delta: Tensor, update: Tensor) -> MovedReference:
    """Step 3: moves the updated entries' reference by Δ, clamped to the image.

    Args:
        reference: (B, W_t, N, 4) reference (x, y, w, h) in [0, 1].
        delta: (B, W_t, N, 2) Δ (x, y) in normalised image units.
        update: (B, W_t, N) bool, entries whose position may change.
    """
    moved = clamp_to_unit(reference[..., :2] + delta)
    displacement = update.unsqueeze(-1).to(moved.dtype) * (moved - reference[..., :2])
    moved = torch.where(update.unsqueeze(-1), moved, reference[..., :2])
    return MovedReference(torch.cat((moved, reference[..., 2:]), dim=-1), displacement)


def fuse_displacement(
    fuser: MLP | None,
    content: Tensor,
    displacement: Tensor | None,
    temperature: float,
    execution: Execution | None = None,
) -> Tensor:
    """Step 4: the features the heads read, the content fused with d's embedding.

    Args:
        fuser: the decoder's ``update_fuser``, or None (the content is returned as is).
        content: (B, W_t, N, C) the layer's output.
        displacement: (B, W_t, N, 2) the masked displacement d, or None without the APU.
        temperature: sine temperature of the embedding.
        execution: how the fuser MLP runs (`taptr.model.layers.MLP`).

    Returns:
        (B, W_t, N, C).
    """
    if fuser is None or displacement is None:
        return content
    embedded = point_embedding(displacement, content.shape[-1] // 2, temperature)
    return fuser(torch.cat((content, embedded), dim=-1), execution)


class Refined(NamedTuple):
    """One layer's positions, as a refinement rule returns them.

    Attributes:
        positions: (B, W_t, N, 4) the layer's reported position logits.
        updated: (B, W_t, N, 4) reported logits of the APU-moved reference, or None.
        reference: (B, W_t, N, 4) the next layer's reference in [0, 1], detached.
        previous: (B, W_t, N, 4) the undetached positions in [0, 1] that the next layer's
            reported positions build on (rules that do not use it pass it through).
    """

    positions: Tensor
    updated: Tensor | None
    reference: Tensor
    previous: Tensor


RefinementRule = Callable[[Tensor, Tensor, Tensor], Refined]
"""(δ from the position head (B, W_t, N, 4), the layer's reference in [0, 1] (moved by the
APU, if any), the previous layer's undetached positions) → `Refined`. TAPTRv2 uses
`refine_updated`; TAPTR v1 and the v2 ablation without the APU use
`taptr.model.v1.decoder.look_forward_twice`."""


def refine_updated(delta: Tensor, reference: Tensor, previous: Tensor) -> Refined:
    """Step 5: positions from the head's δ on top of the APU-moved reference p'.

    Args:
        delta: (B, W_t, N, 4) the position head's output, zero where not updated.
        reference: (B, W_t, N, 4) p' in [0, 1].
        previous: passed through (this rule does not read it).
    """
    updated_logit = inverse_sigmoid(reference)
    # the official outputs re-read the updated position through one more sigmoid round
    # trip than the reference handed to the next layer (≈1e-7 apart)
    updated_output = inverse_sigmoid(updated_logit.sigmoid())
    next_reference = (delta + updated_logit).sigmoid().detach()
    return Refined(delta + updated_output, updated_output, next_reference, previous)
