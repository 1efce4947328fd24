"""TAPTR v1's cost volume: correlation of each point with its frame, sampled around it.

Once per window, every level of each frame's encoder memory is mapped by a 1×1 convolution
and correlated with a projection of each point's window-entry content (scaled by 1/√C).
Each decoder layer then samples a 7×7 window of every level's correlation map around the
layer's input position and hands the 4·49 values to the layer's fuser
(`taptr.model.v1.decoder.V1DecoderLayer`). TAPTRv2 removed this module (its cost grows
with points × tokens).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from taptr.model.execution import Execution
from taptr.model.layers import MLP
from taptr.model.ops import level_start_index
from taptr.model.ops.dense import linear


class CostVolume(nn.Module):
    """Correlation maps per window and their local sampling per layer.

    Shape:
        `prepare`: memory (B·W_t, S, C), content (B·W_t, N, C) → L maps (B·W_t, N, H_l, W_l).
        `sample`: maps, positions (B·W_t, N, 2) → (B·W_t, N, L·(2r + 1)²).
    """

    def __init__(self, d_model: int, num_levels: int, radius: int = 3) -> None:
        super().__init__()
        self.radius = radius
        self.query_proj = MLP(d_model, d_model, d_model, 2)
        self.fmap_mappers = nn.ModuleList(nn.Conv2d(d_model, d_model, 1) for _ in range(num_levels))

    def prepare(
        self,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        content: Tensor,
        execution: Execution | None = None,
    ) -> list[Tensor]:
        """Correlation maps of every point with every level of its own frame.

        Args:
            memory: (B·W_t, S, C) encoder memory (no positional encoding).
            spatial_shapes: (H_l, W_l) per level.
            content: (B·W_t, N, C) window-entry content of each point on each frame.
            execution: how the query MLP runs (`taptr.model.layers.MLP`).

        Returns:
            L maps (B·W_t, N, H_l, W_l).
        """
        frames, points, channels = content.shape
        queries = self.query_proj(content, execution)  # (B·W_t, N, C)
        onednn = execution is not None and execution.onednn_linear
        maps = []
        for mapper, start, (height, width) in zip(
            self.fmap_mappers, level_start_index(spatial_shapes), spatial_shapes, strict=True
        ):
            assert isinstance(mapper, nn.Conv2d)
            tokens = memory[:, start : start + height * width]  # (B·W_t, H·W, C)
            weight = mapper.weight.view(channels, channels)
            # a 1×1 convolution on the tokens
            mapped = linear(tokens, weight, mapper.bias, onednn=onednn)
            correlation = torch.bmm(queries, mapped.transpose(1, 2)) / channels**0.5
            maps.append(correlation.view(frames, points, height, width))
        return maps

    def sample(self, maps: list[Tensor], positions: Tensor) -> Tensor:
        """Bilinear samples of a (2r + 1)² window of each map around each point.

        The official code places the window at level-0 pixel coordinates (x·(H_0 − 1),
        y·(W_0 − 1)) (x scaled by the height: swapped, as for the query initialisation)
        divided by 2^l on level l, samples with align_corners=True and border padding, and
        flattens each window x-offset-major; levels are concatenated finest first.

        Args:
            maps: L maps (B·W_t, N, H_l, W_l) from `prepare`.
            positions: (B·W_t, N, 2) normalised (x, y) in [0, 1].

        Returns:
            (B·W_t, N, L·(2r + 1)²).
        """
        frames, points = positions.shape[:2]
        height0, width0 = maps[0].shape[-2:]
        centre = positions * positions.new_tensor([height0 - 1, width0 - 1])  # (B·W_t, N, 2)
        steps = torch.arange(
            -self.radius, self.radius + 1, dtype=positions.dtype, device=positions.device
        )
        dx, dy = torch.meshgrid(steps, steps, indexing="ij")  # x offset major
        window = torch.stack((dx, dy), -1).view(1, -1, 2)  # (1, K, 2), K = (2r + 1)²
        samples = []
        for level, correlation in enumerate(maps):
            height, width = correlation.shape[-2:]
            pixels = centre.reshape(-1, 1, 2) / 2**level + window  # (B·W_t·N, K, 2)
            scale = pixels.new_tensor([2 / max(width - 1, 1), 2 / max(height - 1, 1)])
            grid = (pixels * scale - 1).unsqueeze(1)  # (B·W_t·N, 1, K, 2)
            image = correlation.reshape(-1, 1, height, width)  # (B·W_t·N, 1, H_l, W_l)
            sampled = F.grid_sample(
                image, grid, mode="bilinear", padding_mode="border", align_corners=True
            )
            samples.append(sampled.view(frames, points, -1))  # (B·W_t, N, K)
        return torch.cat(samples, dim=-1)
