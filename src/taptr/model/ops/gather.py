"""Multi-scale deformable attention as weighted gathers (``embedding_bag``), no layout copies.

Bilinear sampling is a weighted sum of four table rows per location. Folding the
attention weights into the bilinear weights turns a whole deformable-attention output into
one ``embedding_bag`` call per head and query over the rows of the value table, which is
the projection output viewed as (B·S·M, D): no per-level channel-first copies, no large
intermediate of sampled values. Corners outside a map get weight zero (zero padding) and
the same align_corners=False convention as ``grid_sample``, so results equal
`taptr.model.ops.ms_deform_attn` up to float rounding; gradients flow to the values, the
weights and the locations (through the bilinear weights).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from taptr.model.ops.ms_deform_attn import level_start_index


def bilinear_corners(
    locations: Tensor, spatial_shapes: list[tuple[int, int]], tokens: int
) -> tuple[Tensor, Tensor]:
    """Table rows and weights of the four bilinear corners of every sampling location.

    Args:
        locations: (B, Q, M, L, P, 2) locations (x, y) in [0, 1] of each level.
        spatial_shapes: (H_l, W_l) per level.
        tokens: S, tokens per image in the table.

    Returns:
        rows (B, Q, M, L·P, 4) into a (B·S·M, D) table, and weights of the same shape
        (zero for corners outside the map), corners ordered (y0 x0, y0 x1, y1 x0, y1 x1).
    """
    batch, queries, heads, levels, points, _ = locations.shape
    device, dtype = locations.device, locations.dtype
    sizes = torch.tensor(spatial_shapes, device=device).view(levels, 1, 2)  # (H_l, W_l)
    heights, widths = sizes[..., 0], sizes[..., 1]  # (L, 1)
    starts = torch.tensor(level_start_index(spatial_shapes), device=device).view(levels, 1)
    x = locations[..., 0] * widths.to(dtype) - 0.5  # (B, Q, M, L, P) in pixels
    y = locations[..., 1] * heights.to(dtype) - 0.5
    x0, y0 = x.floor(), y.floor()
    fx, fy = x - x0, y - y0
    x0, y0 = x0.long(), y0.long()
    x1, y1 = x0 + 1, y0 + 1
    # outside corners keep a valid row but weigh nothing (zero padding)
    wx0 = (1 - fx) * ((x0 >= 0) & (x0 < widths))
    wx1 = fx * ((x1 >= 0) & (x1 < widths))
    wy0 = (1 - fy) * ((y0 >= 0) & (y0 < heights))
    wy1 = fy * ((y1 >= 0) & (y1 < heights))
    last_x, last_y = widths - 1, heights - 1
    cx0, cx1 = x0.clamp(min=0).minimum(last_x), x1.clamp(min=0).minimum(last_x)
    row0 = starts + y0.clamp(min=0).minimum(last_y) * widths
    row1 = starts + y1.clamp(min=0).minimum(last_y) * widths
    base = torch.arange(batch, device=device).view(batch, 1, 1, 1, 1) * (tokens * heads)
    base = base + torch.arange(heads, device=device).view(1, 1, heads, 1, 1)
    rows = torch.stack((row0 + cx0, row0 + cx1, row1 + cx0, row1 + cx1), -1) * heads
    rows = rows + base.unsqueeze(-1)
    weights = torch.stack((wy0 * wx0, wy0 * wx1, wy1 * wx0, wy1 * wx1), -1)
    shape = (batch, queries, heads, levels * points, 4)
    return rows.view(shape), weights.view(shape)


def gather_sum(table: Tensor, rows: Tensor, weights: Tensor) -> Tensor:
    """Σ_k weights[..., k] · table[rows[..., k]] over the last axis.

    Args:
        table: (R, D) rows.
        rows: (..., K) row indices.
        weights: (..., K).

    Returns:
        (..., D).
    """
    flat_rows = rows.reshape(-1, rows.shape[-1])
    flat_weights = weights.reshape(-1, weights.shape[-1]).to(table.dtype)
    out = F.embedding_bag(flat_rows, table, per_sample_weights=flat_weights, mode="sum")
    return out.view(*rows.shape[:-1], table.shape[-1])


def gather_deform_attn(
    values: Tensor, spatial_shapes: list[tuple[int, int]], locations: Tensor, weights: Tensor
) -> Tensor:
    """Standard deformable attention; same contract as `ms_deform_attn`.

    Args:
        values: (B, S, M, D).
        spatial_shapes: (H_l, W_l) per level.
        locations: (B, Q, M, L, P, 2) in [0, 1].
        weights: (B, Q, M, L, P), softmaxed over (L, P) per head.

    Returns:
        (B, Q, M·D).
    """
    batch, tokens, heads, channels = values.shape
    rows, corner_weights = bilinear_corners(locations, spatial_shapes, tokens)
    combined = corner_weights * weights.flatten(-2).unsqueeze(-1)  # (B, Q, M, L·P, 4)
    out = gather_sum(values.reshape(-1, channels), rows.flatten(-2), combined.flatten(-2))
    return out.view(batch, -1, heads * channels)  # (B, Q, M·D)


def gather_key_aware_attn(
    queries: Tensor,
    keys: Tensor,
    values: Tensor,
    spatial_shapes: list[tuple[int, int]],
    locations: Tensor,
) -> tuple[Tensor, Tensor]:
    """Key-aware deformable attention; same contract as `key_aware_ms_deform_attn`.

    Args:
        queries: (B, Q, M, D) projected queries.
        keys: (B, S, M, D).
        values: (B, S, M, D).
        spatial_shapes: (H_l, W_l) per level.
        locations: (B, Q, M, L, P, 2) in [0, 1].

    Returns:
        output (B, Q, M·D) and pre-softmax logits (B, Q, M, L, P).
    """
    batch, num_queries, heads, channels = queries.shape
    levels, points = locations.shape[3:5]
    rows, corner_weights = bilinear_corners(locations, spatial_shapes, keys.shape[1])
    sampled_keys = gather_sum(keys.reshape(-1, channels), rows, corner_weights)  # (B, Q, M, L·P, D)
    logits = torch.einsum("bqmd,bqmjd->bqmj", queries, sampled_keys) / channels**0.5
    combined = corner_weights * logits.softmax(-1).unsqueeze(-1)  # (B, Q, M, L·P, 4)
    out = gather_sum(values.reshape(-1, channels), rows.flatten(-2), combined.flatten(-2))
    return out.view(batch, num_queries, heads * channels), logits.view(
        batch, num_queries, heads, levels, points
    )
