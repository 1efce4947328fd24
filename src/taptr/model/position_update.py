"""The Attention-based Position Update (APU): move a point where its attention looked.

The cross-attention samples M·L·P locations around the point. The update turns its
attention logits into one weight per sample and moves the point by the weighted mean of
the sampling offsets, in normalised image units. With the disentangler (the paper), an
MLP maps the pre-softmax logits to new weights, softmaxed jointly over all M·L·P samples,
so that position and content attention are decoupled. Without it, the content attention
weights themselves are used and the per-head moves are averaged.
"""

from __future__ import annotations

from torch import Tensor, nn

from taptr.model.layers import MLP


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
    """Position displacement from cross-attention logits and offsets.

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
        self, logits: Tensor, offsets: Tensor, spatial_shapes: list[tuple[int, int]]
    ) -> Tensor:
        """Returns the displacement (Δx, Δy) in normalised image units; nothing is detached."""
        moves = normalize_offsets(offsets, spatial_shapes)  # (B, Q, M, L, P, 2)
        if self.disentangler is not None:
            flat_logits = logits.flatten(2)  # (B, Q, M·L·P), order (head, level, point)
            weights = self.disentangler(flat_logits).softmax(-1)
            return (weights.unsqueeze(-1) * moves.flatten(2, 4)).sum(2)
        weights = logits.flatten(3).softmax(-1)  # (B, Q, M, L·P), per-head content weights
        per_head = (weights.unsqueeze(-1) * moves.flatten(3, 4)).sum(3)  # (B, Q, M, 2)
        return per_head.mean(2)
