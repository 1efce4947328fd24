"""Multi-scale deformable attention as weighted gathers (``embedding_bag``), no layout copies.

Bilinear sampling is a weighted sum of four table rows per location. Folding the
attention weights into the bilinear weights turns a whole deformable-attention output into
one ``embedding_bag`` call over the rows of the value table, which is the projection output
viewed as (B·S·M, D): no per-level channel-first copies and no large intermediate of
sampled values. Each level is padded with a zero border (one cell before, two after, so
that a location clamped onto the far border still has both corners inside) and locations
further out are clamped onto the border, where every corner reads zero. This is exactly
``grid_sample``'s zero padding with align_corners=False, so results equal
`taptr.model.ops.ms_deform_attn` up to float rounding, and gradients flow to the values,
the weights and the locations.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def padded_table(values: Tensor, spatial_shapes: list[tuple[int, int]]) -> Tensor:
    """Values with a zero border around every level, as gather rows.

    Args:
        values: (B, S, M, D), levels flattened row-major.
        spatial_shapes: (H_l, W_l) per level.

    Returns:
        (B · Σ(H_l + 3)(W_l + 3) · M, D).
    """
    batch, _, heads, channels = values.shape
    parts, start = [], 0
    for height, width in spatial_shapes:
        level = values[:, start : start + height * width].view(
            batch, height, width, heads, channels
        )
        parts.append(F.pad(level, (0, 0, 0, 0, 1, 2, 1, 2)).flatten(1, 2))  # (B, (H+3)(W+3), M, D)
        start += height * width
    return torch.cat(parts, dim=1).reshape(-1, channels)


def bilinear_corners(
    locations: Tensor, spatial_shapes: list[tuple[int, int]], scale: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Rows of the padded table and weights of the four corners of every location.

    Args:
        locations: (B, Q, M, L, P, 2) locations (x, y) in [0, 1] of each level.
        spatial_shapes: (H_l, W_l) per level.
        scale: optional (B, Q, M, L, P) factor folded into the weights.

    Returns:
        rows (B, Q, M, L·P, 4) into `padded_table`, and weights of the same shape, corners
        ordered (y0 x0, y0 x1, y1 x0, y1 x1).
    """
    batch, queries, heads, levels, points, _ = locations.shape
    device, dtype = locations.device, locations.dtype
    sizes = torch.tensor(spatial_shapes, device=device, dtype=dtype).view(levels, 1, 2).flip(-1)
    padded = [(h + 3) * (w + 3) for h, w in spatial_shapes]
    starts = torch.tensor([sum(padded[:i]) for i in range(levels)], device=device).view(levels, 1)
    row_length = torch.tensor([w + 3 for _, w in spatial_shapes], device=device).view(levels, 1)
    pixels = locations * sizes - 0.5  # (B, Q, M, L, P, 2) as (x, y) in each level's pixels
    # beyond one cell outside, every corner is in the zero border: clamp onto it
    pixels = torch.maximum(torch.minimum(pixels, sizes), pixels.new_tensor(-1.0))
    corner = pixels.floor()
    frac = pixels - corner
    cell = (corner + 1).long()  # padded coordinates of the top-left corner
    # table row of (image b, token s, head m) is (b·S_pad + s)·M + m
    image_head = torch.arange(batch, device=device).view(batch, 1, 1, 1, 1) * (sum(padded) * heads)
    image_head = image_head + torch.arange(heads, device=device).view(1, 1, heads, 1, 1)
    top_left = image_head + (starts + cell[..., 1] * row_length + cell[..., 0]) * heads
    steps = torch.stack(
        (torch.zeros_like(row_length), torch.ones_like(row_length), row_length, row_length + 1), -1
    )
    rows = top_left.unsqueeze(-1) + steps * heads  # (B, Q, M, L, P, 4)
    wx = torch.stack((1 - frac[..., 0], frac[..., 0]), -1)  # (B, Q, M, L, P, 2)
    wy = torch.stack((1 - frac[..., 1], frac[..., 1]), -1)
    if scale is not None:
        wy = wy * scale.unsqueeze(-1)
    weights = (wy.unsqueeze(-1) * wx.unsqueeze(-2)).flatten(-2)  # (B, Q, M, L, P, 4)
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
    batch, _, heads, channels = values.shape
    rows, combined = bilinear_corners(locations, spatial_shapes, scale=weights)
    table = padded_table(values, spatial_shapes)
    out = gather_sum(table, rows.flatten(-2), combined.flatten(-2))  # (B, Q, M, D)
    return out.view(batch, -1, heads * channels)


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
    rows, corner_weights = bilinear_corners(locations, spatial_shapes)
    sampled_keys = gather_sum(
        padded_table(keys, spatial_shapes), rows, corner_weights
    )  # (B, Q, M, L·P, D)
    logits = torch.einsum("bqmd,bqmjd->bqmj", queries, sampled_keys) / channels**0.5
    combined = corner_weights * logits.softmax(-1).unsqueeze(-1)  # (B, Q, M, L·P, 4)
    table = padded_table(values, spatial_shapes)
    out = gather_sum(table, rows.flatten(-2), combined.flatten(-2))
    return out.view(batch, num_queries, heads * channels), logits.view(
        batch, num_queries, heads, levels, points
    )
