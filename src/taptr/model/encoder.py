"""The deformable encoder: post-norm layers over each frame's multi-scale tokens.

Each token attends with `DeformableAttention` around its own cell centre, the same
normalised reference on every level. The sine position encoding plus a learned level
embedding is added to the queries only; the decoder never sees it.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from taptr.model.attention import DeformableAttention
from taptr.model.execution import Execution
from taptr.model.layers import MLP
from taptr.model.ops.constants import kept
from taptr.model.ops.row_blocks import use_row_blocks
from taptr.model.position_encoding import feature_map_encoding


def reference_grid(spatial_shapes: list[tuple[int, int]], device: torch.device) -> Tensor:
    """Cell centres ((j + 0.5) / W_l, (i + 0.5) / H_l) of every level, in float32.

    Made once per shape and device (`taptr.model.ops.constants.kept`); never write to it.

    Returns:
        (S, 2) as (x, y), levels concatenated, row-major inside a level.
    """
    return kept(
        ("reference grid", tuple(spatial_shapes), device), lambda: _grid(spatial_shapes, device)
    )


def _grid(spatial_shapes: list[tuple[int, int]], device: torch.device) -> Tensor:
    grids = []
    for height, width in spatial_shapes:
        ys, xs = torch.meshgrid(
            torch.linspace(0.5, height - 0.5, height, dtype=torch.float32, device=device),
            torch.linspace(0.5, width - 0.5, width, dtype=torch.float32, device=device),
            indexing="ij",
        )
        grids.append(torch.stack((xs.reshape(-1) / width, ys.reshape(-1) / height), -1))
    return torch.cat(grids)


class EncoderLayer(nn.Module):
    """Deformable self-attention then FFN, each followed by a residual LayerNorm.

    Shape:
        tokens (B, S, C), position (B, S, C), reference (B, S, 2) → (B, S, C).
    """

    def __init__(self, attention: DeformableAttention, d_model: int, ffn_dim: int) -> None:
        super().__init__()
        self.attention = attention
        self.norm_attention = nn.LayerNorm(d_model)
        self.ffn = MLP(d_model, ffn_dim, d_model, num_layers=2)
        self.norm_ffn = nn.LayerNorm(d_model)

    def forward(
        self,
        tokens: Tensor,
        position: Tensor,
        reference: Tensor,
        spatial_shapes: list[tuple[int, int]],
        execution: Execution,
    ) -> Tensor:
        """Runs one post-norm layer the way ``execution`` says.

        Only the attention's value table needs every token; the rest of the layer is row
        by row. So at inference with an encoder block (`Execution.encoder_block`) the
        tokens go through it a block at a time, with every intermediate (sampling
        locations, corner rows and weights, the FFN's hidden activation) small enough to
        stay in the cache instead of a full-frame tensor each: the same arithmetic per row.
        """
        values = self.attention.values(tokens, spatial_shapes, execution)
        block = execution.encoder_block
        if block is None or not use_row_blocks(self, tokens, block):
            return self._update(tokens, position, reference, values, spatial_shapes, execution)
        out = torch.empty_like(tokens)  # (B, S, C)
        for start in range(0, tokens.shape[1], block):
            rows = slice(start, start + block)
            out[:, rows] = self._update(
                tokens[:, rows],
                position[:, rows],
                reference[:, rows],
                values,
                spatial_shapes,
                execution,
            )
        return out

    def _update(
        self,
        tokens: Tensor,
        position: Tensor,
        reference: Tensor,
        values: Tensor,
        spatial_shapes: list[tuple[int, int]],
        execution: Execution,
    ) -> Tensor:
        """The layer on some of the tokens (B, Q, C), attending to the values of all."""
        attended = self.attention.attend(
            tokens + position, reference, values, spatial_shapes, execution
        ).output
        tokens = self.norm_attention(tokens + attended)
        return self.norm_ffn(tokens + self.ffn(tokens, execution))


class Encoder(nn.Module):
    """Stack of encoder layers with the sine + level position encoding.

    Shape:
        list of L maps (B, C, H_l, W_l) → memory (B, S, C), S = Σ H_l·W_l.
    """

    def __init__(
        self, layers: list[EncoderLayer], d_model: int, temperature: float, num_levels: int
    ):
        super().__init__()
        self.layers = nn.ModuleList(layers)
        self.level_embed = nn.Parameter(torch.empty(num_levels, d_model))
        self.temperature = temperature
        nn.init.normal_(self.level_embed)

    def position_encoding(
        self, spatial_shapes: list[tuple[int, int]], dtype: torch.dtype
    ) -> Tensor:
        """Sine encoding of every token plus its level embedding, (S, C).

        The sine part and each token's level are made once per shape (`kept`).
        """
        channels = self.level_embed.shape[1] // 2
        device = self.level_embed.device
        shapes = tuple(spatial_shapes)

        def sines() -> Tensor:  # (S, C)
            maps = [
                feature_map_encoding(h, w, channels, self.temperature, device) for h, w in shapes
            ]
            return torch.cat(maps).to(dtype)

        def levels() -> Tensor:  # (S,) level of each token
            sizes = torch.tensor([h * w for h, w in shapes], device=device)
            return torch.repeat_interleave(torch.arange(len(shapes), device=device), sizes)

        sine = kept(("map encoding", shapes, channels, self.temperature, device, dtype), sines)
        level = kept(("token levels", shapes, device), levels)
        return sine + self.level_embed[level]

    def forward(self, maps: list[Tensor], execution: Execution) -> Tensor:
        """Encodes the flattened multi-scale tokens of each image the way ``execution`` says."""
        spatial_shapes = [(m.shape[-2], m.shape[-1]) for m in maps]
        tokens = torch.cat([m.flatten(2).transpose(1, 2) for m in maps], dim=1)  # (B, S, C)
        if not self.layers:
            return tokens
        position = self.position_encoding(spatial_shapes, tokens.dtype)  # (S, C)
        reference = reference_grid(spatial_shapes, tokens.device).to(tokens.dtype)  # (S, 2)
        batch = tokens.shape[0]
        position = position.unsqueeze(0).expand(batch, -1, -1)
        reference = reference.unsqueeze(0).expand(batch, -1, -1)
        for layer in self.layers:
            tokens = layer(tokens, position, reference, spatial_shapes, execution)
        return tokens
