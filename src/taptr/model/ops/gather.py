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
from torch import Tensor, nn

CHUNK_ELEMENTS = 1 << 24
"""Largest intermediate of sampled keys, in elements (64 MB in float32)."""


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


def projected_table(
    memory: Tensor, projection: nn.Linear, spatial_shapes: list[tuple[int, int]], heads: int
) -> Tensor:
    """`padded_table` of ``projection(memory)`` split into heads, built in one pass.

    Without gradients, the projection's matrix product is written straight into the padded
    layout together with its bias (only the borders are zeroed), which saves the bias
    broadcast, the padding and the concatenation copies of the plain formulation; with
    gradients, the plain (differentiable) formulation is used.

    Args:
        memory: (B, S, C) tokens.
        projection: the value or key projection (C → C).
        spatial_shapes: (H_l, W_l) per level.
        heads: attention heads M.

    Returns:
        (B · Σ(H_l + 3)(W_l + 3) · M, C / M).
    """
    batch, tokens, channels = memory.shape
    if torch.is_grad_enabled() and (memory.requires_grad or projection.weight.requires_grad):
        return padded_table(projection(memory).view(batch, tokens, heads, -1), spatial_shapes)
    product = torch.matmul(memory, projection.weight.t())  # (B, S, C) without the bias
    padded_sizes = [(h + 3) * (w + 3) for h, w in spatial_shapes]
    table = memory.new_empty(batch, sum(padded_sizes), channels)
    start, padded_start = 0, 0
    for (height, width), size in zip(spatial_shapes, padded_sizes, strict=True):
        level = table[:, padded_start : padded_start + size].view(
            batch, height + 3, width + 3, channels
        )
        level[:, 0].zero_()
        level[:, height + 1 :].zero_()
        level[:, 1 : height + 1, 0].zero_()
        level[:, 1 : height + 1, width + 1 :].zero_()
        interior = product[:, start : start + height * width].view(batch, height, width, channels)
        torch.add(interior, projection.bias, out=level[:, 1 : height + 1, 1 : width + 1])
        start, padded_start = start + height * width, padded_start + size
    return table.view(-1, channels // heads)


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
    # int32 rows halve the traffic of the index arithmetic while the table fits
    index = torch.int32 if batch * sum(padded) * heads < 2**31 else torch.int64
    starts = torch.tensor([sum(padded[:i]) for i in range(levels)], device=device, dtype=index)
    starts = starts.view(levels, 1)
    row_length = torch.tensor([w + 3 for _, w in spatial_shapes], device=device, dtype=index)
    row_length = row_length.view(levels, 1)
    pixels = locations * sizes - 0.5  # (B, Q, M, L, P, 2) as (x, y) in each level's pixels
    # beyond one cell outside, every corner is in the zero border: clamp onto it
    pixels = torch.maximum(torch.minimum(pixels, sizes), pixels.new_tensor(-1.0))
    corner = pixels.floor()
    frac = pixels - corner
    cell = (corner + 1).to(index)  # padded coordinates of the top-left corner
    # table row of (image b, token s, head m) is (b·S_pad + s)·M + m
    image_head = torch.arange(batch, device=device, dtype=index).view(batch, 1, 1, 1, 1)
    image_head = image_head * (sum(padded) * heads)
    image_head = image_head + torch.arange(heads, device=device, dtype=index).view(
        1, 1, heads, 1, 1
    )
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
    table: Tensor, spatial_shapes: list[tuple[int, int]], locations: Tensor, weights: Tensor
) -> Tensor:
    """Standard deformable attention; `ms_deform_attn` on a `padded_table` of the values.

    Args:
        table: (B · S_pad · M, D) values as built by `padded_table` or `projected_table`.
        spatial_shapes: (H_l, W_l) per level.
        locations: (B, Q, M, L, P, 2) in [0, 1].
        weights: (B, Q, M, L, P), softmaxed over (L, P) per head.

    Returns:
        (B, Q, M·D).
    """
    batch, queries, heads = locations.shape[:3]
    rows, combined = bilinear_corners(locations, spatial_shapes, scale=weights)
    out = gather_sum(table, rows.flatten(-2), combined.flatten(-2))  # (B, Q, M, D)
    return out.view(batch, queries, heads * table.shape[-1])


def gather_key_aware_attn(
    queries: Tensor,
    key_table: Tensor,
    value_table: Tensor,
    spatial_shapes: list[tuple[int, int]],
    locations: Tensor,
) -> tuple[Tensor, Tensor]:
    """Key-aware deformable attention; `key_aware_ms_deform_attn` on padded tables.

    Args:
        queries: (B, Q, M, D) projected queries.
        key_table: (B · S_pad · M, D) keys, see `padded_table` / `projected_table`.
        value_table: (B · S_pad · M, D) values.
        spatial_shapes: (H_l, W_l) per level.
        locations: (B, Q, M, L, P, 2) in [0, 1].

    Returns:
        output (B, Q, M·D) and pre-softmax logits (B, Q, M, L, P).
    """
    batch, num_queries, heads, channels = queries.shape
    levels, points = locations.shape[3:5]
    rows, corner_weights = bilinear_corners(locations, spatial_shapes)
    # sampled keys are (B, Q, M, L·P, D): bound their memory by taking queries in chunks
    chunk = max(1, CHUNK_ELEMENTS // (batch * heads * levels * points * channels))
    logits = (
        torch.cat(
            [
                torch.einsum(
                    "bqmd,bqmjd->bqmj",
                    queries[:, start : start + chunk],
                    gather_sum(
                        key_table,
                        rows[:, start : start + chunk],
                        corner_weights[:, start : start + chunk],
                    ),
                )
                for start in range(0, num_queries, chunk)
            ],
            dim=1,
        )
        / channels**0.5
    )  # (B, Q, M, L·P)
    combined = corner_weights * logits.softmax(-1).unsqueeze(-1)  # (B, Q, M, L·P, 4)
    out = gather_sum(value_table, rows.flatten(-2), combined.flatten(-2))
    return out.view(batch, num_queries, heads * channels), logits.view(
        batch, num_queries, heads, levels, points
    )
