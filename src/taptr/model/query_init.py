"""Initial content of each point query: the encoder memory sampled at its start position.

Every level of the start frame's memory is sampled bilinearly (align_corners=True, border
padding) and the L samples are concatenated and projected to d_model.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from taptr.geometry import sample_at_pixels
from taptr.model.ops import level_start_index


def memory_maps(memory: Tensor, spatial_shapes: list[tuple[int, int]]) -> list[Tensor]:
    """Splits flattened tokens back into maps.

    Args:
        memory: (B, S, C).
        spatial_shapes: (H_l, W_l) per level.

    Returns:
        L maps (B, C, H_l, W_l).
    """
    batch, _, channels = memory.shape
    return [
        memory[:, start : start + h * w].transpose(1, 2).reshape(batch, channels, h, w)
        for start, (h, w) in zip(level_start_index(spatial_shapes), spatial_shapes, strict=True)
    ]


class QueryInitializer(nn.Module):
    """Samples each level at the point and projects the concatenation to d_model.

    Shape:
        memory (B, S, C), positions (B, N, 2) → content (B, N, C).
    """

    def __init__(self, d_model: int, num_levels: int) -> None:
        super().__init__()
        self.project = nn.Linear(num_levels * d_model, d_model)

    def sample(
        self, memory: Tensor, spatial_shapes: list[tuple[int, int]], positions: Tensor
    ) -> Tensor:
        """Concatenated per-level samples, before the projection.

        The official code scales x by (H_l − 1) and y by (W_l − 1), swapped with respect to
        the map's axes; this only matters for non-square maps and is kept so that released
        weights reproduce.

        Args:
            memory: (B, S, C) encoder output of one frame per video.
            spatial_shapes: (H_l, W_l) per level.
            positions: (B, N, 2) normalised (x, y) in [0, 1].

        Returns:
            (B, N, L·C).
        """
        samples = []
        for level_map, (height, width) in zip(
            memory_maps(memory, spatial_shapes), spatial_shapes, strict=True
        ):
            scale = positions.new_tensor([height - 1, width - 1])
            samples.append(sample_at_pixels(level_map, positions * scale))  # (B, N, C)
        return torch.cat(samples, dim=-1)

    def forward(
        self, memory: Tensor, spatial_shapes: list[tuple[int, int]], positions: Tensor
    ) -> Tensor:
        """Initial content of points starting on the frame that ``memory`` encodes."""
        return self.project(self.sample(memory, spatial_shapes, positions))
