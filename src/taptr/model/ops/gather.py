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


def interleaved_sizes(spatial_shapes: list[tuple[int, int]], points: int, like: Tensor) -> Tensor:
    """(W_l, H_l) of every level, repeated for its points: (L · P · 2) as x, y pairs.

    Elementwise ops between (..., L · P · 2) rows and this vector run along one contiguous
    axis, where broadcasting a (L, 1, 2) size over (..., L, P, 2) runs an inner loop of two.
    """
    sizes = like.new_tensor([[w, h] for h, w in spatial_shapes])  # (L, 2)
    levels = len(spatial_shapes)
    return sizes.view(levels, 1, 2).expand(levels, points, 2).reshape(-1)


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
    device = locations.device
    padded = [(h + 3) * (w + 3) for h, w in spatial_shapes]
    # int32 rows halve the traffic of the index arithmetic while the table fits
    index = torch.int32 if batch * sum(padded) * heads < 2**31 else torch.int64
    sizes = interleaved_sizes(spatial_shapes, points, locations)  # (L·P·2)
    pixels = locations.flatten(3) * sizes - 0.5  # (B, Q, M, L·P·2) in each level's pixels
    # beyond one cell outside, every corner is in the zero border: clamp onto it
    pixels = torch.minimum(pixels, sizes).clamp_(min=-1.0)
    corner = pixels.floor()
    frac = (pixels - corner).view(locations.shape)
    cell = corner.to(index).add_(1).view(locations.shape)  # padded coordinates of top-left
    starts = torch.tensor([sum(padded[:i]) for i in range(levels)], device=device, dtype=index)
    row_length = torch.tensor([w + 3 for _, w in spatial_shapes], device=device, dtype=index)
    starts, row_length = starts.view(levels, 1), row_length.view(levels, 1)
    # table row of (image b, token s, head m) is (b·S_pad + s)·M + m
    image_head = torch.arange(batch, device=device, dtype=index).view(batch, 1, 1, 1, 1)
    image_head = image_head * (sum(padded) * heads)
    image_head = image_head + torch.arange(heads, device=device, dtype=index).view(
        1, 1, heads, 1, 1
    )
    top_left = image_head + (starts + cell[..., 1] * row_length + cell[..., 0]) * heads
    # corners are written into strided slices: stacking them costs several times more
    rows = top_left.new_empty(*top_left.shape, 4)  # (B, Q, M, L, P, 4)
    rows[..., 0] = top_left
    torch.add(top_left, heads, out=rows[..., 1])
    torch.add(top_left, row_length * heads, out=rows[..., 2])
    torch.add(rows[..., 2], heads, out=rows[..., 3])
    fx, fy = frac[..., 0], frac[..., 1]
    gx, gy = 1 - fx, 1 - fy
    if scale is not None:
        fy, gy = fy * scale, gy * scale
    if torch.is_grad_enabled() and (fx.requires_grad or fy.requires_grad):
        weights = torch.stack((gy * gx, gy * fx, fy * gx, fy * fx), -1)  # out= has no autograd
    else:
        weights = fx.new_empty(*fx.shape, 4)
        torch.mul(gy, gx, out=weights[..., 0])
        torch.mul(gy, fx, out=weights[..., 1])
        torch.mul(fy, gx, out=weights[..., 2])
        torch.mul(fy, fx, out=weights[..., 3])
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
