"""TAPTRv3's point initialisation: the content and its K × K context on the start frame.

Every level of the start frame's memory is sampled at the point and at its K × K
neighbourhood, one feature pixel apart (align_corners=True pixels, border padding, as
TAPTRv2's query initialiser), and each of the K² level-concatenated samples goes through
the same projection. The centre is the point's content, the whole patch its context for
the context-aware cross-attention. Unlike TAPTRv2, x is scaled by W_l − 1 and y by
H_l − 1 (the official v3 code fixed the swap here, and only here).
"""

from __future__ import annotations

import torch
from torch import Tensor

from taptr.geometry import sample_at_pixels
from taptr.model.ops.context_patches import patch_steps
from taptr.model.query_init import QueryInitializer, memory_maps


class ContextInitializer(QueryInitializer):
    """Samples each level around the point and projects every sample of the patch.

    Attributes:
        patch: side K of the context patch.

    Shape:
        memory (B, S, C), positions (B, N, 2) → context (B, N, K, K, C).
    """

    def __init__(self, d_model: int, num_levels: int, patch: int) -> None:
        super().__init__(d_model, num_levels)
        self.patch = patch

    def sample(
        self, memory: Tensor, spatial_shapes: list[tuple[int, int]], positions: Tensor
    ) -> Tensor:
        """Concatenated per-level samples of each patch, before the projection.

        Args:
            memory: (B, S, C) encoder output of one frame per video.
            spatial_shapes: (H_l, W_l) per level.
            positions: (B, N, 2) normalised (x, y) in [0, 1].

        Returns:
            (B, N, K², L·C), patch index a·K + b for steps (dx, dy) = (offsets[a], offsets[b]).
        """
        batch, points = positions.shape[:2]
        steps = patch_steps(self.patch, positions)  # (K², 2)
        samples = []
        for level_map, (height, width) in zip(
            memory_maps(memory, spatial_shapes), spatial_shapes, strict=True
        ):
            scale = positions.new_tensor([width - 1, height - 1])
            pixels = (positions * scale).unsqueeze(2) + steps  # (B, N, K², 2)
            sampled = sample_at_pixels(level_map, pixels.flatten(1, 2))  # (B, N·K², C)
            samples.append(sampled.view(batch, points, len(steps), -1))
        return torch.cat(samples, dim=-1)

    def forward(
        self, memory: Tensor, spatial_shapes: list[tuple[int, int]], positions: Tensor
    ) -> Tensor:
        """The (B, N, K, K, C) context of points starting on the frame ``memory`` encodes."""
        projected = self.project(self.sample(memory, spatial_shapes, positions))
        return projected.unflatten(2, (self.patch, self.patch))


def centre(context: Tensor) -> Tensor:
    """The point's content: the middle of its (..., K, K, C) context, (..., C)."""
    middle = context.shape[-2] // 2
    return context[..., middle, middle, :]
