"""Attention modules: deformable (encoder), key-aware deformable (decoder), and plain MHA.

Both deformable variants return a `DeformableOutput` so that the position update can read
the pre-softmax logits and the raw sampling offsets, whichever variant produced them.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from taptr.model.execution import Execution
from taptr.model.frame_tables import LayerTables
from taptr.model.ops import deform_attn, key_aware_attn, value_table
from taptr.model.ops.dense import apply_linear, linear
from taptr.model.ops.gather import interleaved_sizes


class DeformableOutput(NamedTuple):
    """Result of a deformable attention call.

    Attributes:
        output: (B, Q, C) attended features, after the output projection.
        logits: (B, Q, M, L, P) pre-softmax attention logits.
        offsets: (B, Q, M, L, P, 2) raw sampling offsets (x, y) in feature-pixel units.
    """

    output: Tensor
    logits: Tensor
    offsets: Tensor


def _offset_grid_bias(num_heads: int, num_levels: int, num_points: int) -> Tensor:
    """Deformable DETR's start: head h looks along angle 2πh/M, point p at distance p + 1."""
    angles = torch.arange(num_heads, dtype=torch.float32) * (2.0 * math.pi / num_heads)
    grid = torch.stack([angles.cos(), angles.sin()], -1)  # (M, 2)
    grid = grid / grid.abs().max(-1, keepdim=True)[0]
    grid = grid.view(num_heads, 1, 1, 2).repeat(1, num_levels, num_points, 1)
    grid *= torch.arange(1, num_points + 1, dtype=torch.float32).view(1, 1, -1, 1)
    return grid.flatten()


def project(layer: nn.Linear, x: Tensor, execution: Execution) -> Tensor:
    """``layer(x)``, as a oneDNN inner product where the execution asks for it."""
    return apply_linear(layer, x, onednn=execution.onednn_linear)


def sampling_locations(
    reference: Tensor, offsets: Tensor, spatial_shapes: list[tuple[int, int]]
) -> Tensor:
    """Locations = reference + offset / (W_l, H_l), in [0, 1] per level.

    Args:
        reference: (B, Q, 2) reference (x, y) in [0, 1].
        offsets: (B, Q, M, L, P, 2) offsets (x, y) in feature pixels of each level.
        spatial_shapes: (H_l, W_l) per level.

    Returns:
        (B, Q, M, L, P, 2).
    """
    levels, points = offsets.shape[3:5]
    sizes = interleaved_sizes(spatial_shapes, points, offsets)  # (L·P·2) as (W_l, H_l) pairs
    start = reference.repeat(1, 1, levels * points).unsqueeze(2)  # (B, Q, 1, L·P·2)
    return (offsets.flatten(3) / sizes + start).view(offsets.shape)


class DeformableAttention(nn.Module):
    """Multi-scale deformable attention with learned attention weights.

    Used by the encoder, and by the decoder when ``cross_attention="standard"``.

    Shape:
        query (B, Q, C), reference (B, Q, 2), memory (B, S, C) → output (B, Q, C).
    """

    def __init__(self, d_model: int, num_heads: int, num_levels: int, num_points: int) -> None:
        super().__init__()
        self.num_heads, self.num_levels, self.num_points = num_heads, num_levels, num_points
        samples = num_heads * num_levels * num_points
        self.sampling_offsets = nn.Linear(d_model, samples * 2)
        self.attention_weights = nn.Linear(d_model, samples)
        self.value_proj = nn.Linear(d_model, d_model)
        self.output_proj = nn.Linear(d_model, d_model)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Deformable DETR's initialisation: zero offsets around a radial grid, uniform weights."""
        nn.init.zeros_(self.sampling_offsets.weight)
        with torch.no_grad():
            self.sampling_offsets.bias.copy_(
                _offset_grid_bias(self.num_heads, self.num_levels, self.num_points)
            )
        nn.init.zeros_(self.attention_weights.weight)
        nn.init.zeros_(self.attention_weights.bias)
        for proj in (self.value_proj, self.output_proj):
            nn.init.xavier_uniform_(proj.weight)
            nn.init.zeros_(proj.bias)

    def values(
        self, memory: Tensor, spatial_shapes: list[tuple[int, int]], execution: Execution
    ) -> Tensor:
        """The memory's projected values, laid out for ``execution.kernel`` (`value_table`).

        Args:
            memory: (B, S, C) flattened multi-scale tokens.
            spatial_shapes: (H_l, W_l) of the L levels.
            execution: how to run.
        """
        return value_table(
            execution.kernel,
            memory,
            self.value_proj,
            spatial_shapes,
            self.num_heads,
            onednn=execution.onednn_linear,
        )

    def attend(
        self,
        query: Tensor,
        reference: Tensor,
        values: Tensor,
        spatial_shapes: list[tuple[int, int]],
        execution: Execution,
    ) -> DeformableOutput:
        """Attends from each query to values made by `values` around its reference point.

        Queries are independent of each other: any subset of them gives the same rows.

        Args:
            query: (B, Q, C) queries, position embedding already added.
            reference: (B, Q, 2) reference (x, y) in [0, 1].
            values: `values` of the memory, made with the same execution.
            spatial_shapes: (H_l, W_l) of the L levels.
            execution: how to run; its ``kernel`` samples the values.
        """
        batch, queries, _ = query.shape
        m, lv, p = self.num_heads, self.num_levels, self.num_points
        offsets = project(self.sampling_offsets, query, execution).view(batch, queries, m, lv, p, 2)
        logits = project(self.attention_weights, query, execution).view(batch, queries, m, lv * p)
        weights = logits.softmax(-1).view(batch, queries, m, lv, p)
        locations = sampling_locations(reference, offsets, spatial_shapes)
        output = deform_attn(execution.kernel, values, spatial_shapes, locations, weights)
        return DeformableOutput(
            project(self.output_proj, output, execution),
            logits.view(batch, queries, m, lv, p),
            offsets,
        )

    def forward(
        self,
        query: Tensor,
        reference: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        execution: Execution,
    ) -> DeformableOutput:
        """`attend` to the `values` of ``memory`` (B, S, C), the flattened tokens."""
        values = self.values(memory, spatial_shapes, execution)
        return self.attend(query, reference, values, spatial_shapes, execution)


class KeyAwareDeformableAttention(nn.Module):
    """TAPTRv2's key-aware deformable attention (no learned attention-weight layer).

    Keys and values are projections of the memory alone (no positional encoding); the
    weights are softmaxed dot products between the projected query and the sampled keys.
    The offsets come from the unprojected query.

    Shape:
        query (B, Q, C), reference (B, Q, 2), memory (B, S, C) → output (B, Q, C).
    """

    def __init__(self, d_model: int, num_heads: int, num_levels: int, num_points: int) -> None:
        super().__init__()
        self.num_heads, self.num_levels, self.num_points = num_heads, num_levels, num_points
        self.sampling_offsets = nn.Linear(d_model, num_heads * num_levels * num_points * 2)
        self.value_proj = nn.Linear(d_model, d_model)
        self.key_proj = nn.Linear(d_model, d_model)
        self.query_proj = nn.Linear(d_model, d_model)
        self.output_proj = nn.Linear(d_model, d_model)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Radial-grid offset bias; the weights follow the transformer's xavier init."""
        nn.init.xavier_uniform_(self.sampling_offsets.weight)
        with torch.no_grad():
            self.sampling_offsets.bias.copy_(
                _offset_grid_bias(self.num_heads, self.num_levels, self.num_points)
            )
        for proj in (self.value_proj, self.key_proj, self.query_proj, self.output_proj):
            nn.init.xavier_uniform_(proj.weight)
            nn.init.zeros_(proj.bias)

    def forward(
        self,
        query: Tensor,
        reference: Tensor,
        memory: Tensor,
        spatial_shapes: list[tuple[int, int]],
        execution: Execution,
        tables: LayerTables | None = None,
    ) -> DeformableOutput:
        """Attends from each query to keys and values sampled around its reference point.

        Args:
            query: (B, Q, C) queries, position embedding already added.
            reference: (B, Q, 2) reference (x, y) in [0, 1].
            memory: (B, S, C) flattened multi-scale tokens.
            spatial_shapes: (H_l, W_l) of the L levels.
            execution: how to run; its ``kernel`` samples the keys and values.
            tables: with the ``gather`` kernel, where this layer's key and value tables of
                each image come from (made once per frame and shared by the windows that
                hold it, `taptr.model.frame_tables`); without it they are made here.
        """
        batch, queries, _ = query.shape
        m, lv, p = self.num_heads, self.num_levels, self.num_points
        projected = project(self.query_proj, query, execution).view(batch, queries, m, -1)
        offsets = project(self.sampling_offsets, query, execution).view(batch, queries, m, lv, p, 2)
        locations = sampling_locations(reference, offsets, spatial_shapes)
        # lazy: nothing is projected unless the gather kernel reads them
        onednn = execution.onednn_linear
        images = (
            None
            if tables is None
            else tables.images(memory, self.key_proj, self.value_proj, onednn=onednn)
        )
        output, logits = key_aware_attn(
            execution.kernel,
            projected,
            memory,
            self.key_proj,
            self.value_proj,
            spatial_shapes,
            locations,
            images,
            onednn=onednn,
        )
        return DeformableOutput(project(self.output_proj, output, execution), logits, offsets)


class MultiheadAttention(nn.Module):
    """Multi-head attention with a boolean "allowed" mask shared by all heads.

    Parameter names match ``torch.nn.MultiheadAttention`` (packed q, k, v input projection)
    so checkpoints map one to one; the mask is broadcast over heads instead of being
    materialised per head.

    Shape:
        query, key (B, L, C), value (B, L, C), allowed (B, 1, L, L) → (B, L, C).
    """

    def __init__(self, d_model: int, num_heads: int) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.in_proj_weight = nn.Parameter(torch.empty(3 * d_model, d_model))
        self.in_proj_bias = nn.Parameter(torch.zeros(3 * d_model))
        self.out_proj = nn.Linear(d_model, d_model)
        nn.init.xavier_uniform_(self.in_proj_weight)
        nn.init.zeros_(self.out_proj.bias)

    def forward(
        self,
        query: Tensor,
        key: Tensor,
        value: Tensor,
        allowed: Tensor | None,
        *,
        onednn: bool = False,
    ) -> Tensor:
        """Scaled dot-product attention; ``allowed[b, 0, i, j]`` False blocks i → j.

        ``onednn`` runs the projections as oneDNN inner products where that applies
        (`taptr.model.ops.dense`).
        """
        batch, length, channels = query.shape
        w_q, w_k, w_v = self.in_proj_weight.chunk(3)
        b_q, b_k, b_v = self.in_proj_bias.chunk(3)

        def heads(x: Tensor, w: Tensor, b: Tensor) -> Tensor:
            # (B, L, C) → (B, M, L, D)
            return (
                linear(x, w, b, onednn=onednn)
                .view(batch, -1, self.num_heads, channels // self.num_heads)
                .transpose(1, 2)
            )

        attended = F.scaled_dot_product_attention(
            heads(query, w_q, b_q),
            heads(key, w_k, b_k),
            heads(value, w_v, b_v),
            attn_mask=allowed,
        )  # (B, M, L, D)
        merged = attended.transpose(1, 2).reshape(batch, length, channels)  # (B, L, C)
        return apply_linear(self.out_proj, merged, onednn=onednn)
