"""Multi-scale deformable attention as weighted gathers (``embedding_bag``), no layout copies.

Bilinear sampling is a weighted sum of four table rows per location. Folding the
attention weights into the bilinear weights turns a whole deformable-attention output into
one ``embedding_bag`` call over the rows of the value table, which is the projection output
viewed as (B·S·M, D): no per-level channel-first copies and no large intermediate of
sampled values. Both give ``grid_sample``'s zero padding with align_corners=False, so
results equal `taptr.model.ops.ms_deform_attn` up to float rounding, and gradients flow to
the values, the weights and the locations. Corners outside a level are handled one of two
ways (``border``):

- a zero border in the table (``border=True``): each level padded by one cell before and
  two after, locations further out clamped onto it, where every corner reads zero. Building
  the padded table costs a strided copy of the projection; the per-location work is small.
  Best for the encoder, whose queries are as many as the table's rows.
- weights set to zero (``border=False``): the table is the plain projection (one ``addmm``)
  and every corner outside its level gets weight zero and a row clamped inside. Best for
  the decoder, which builds ten tables per window for a few hundred points.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from taptr.model.ops.constants import kept
from taptr.model.ops.dense import apply_linear, bfloat16_mode, linear

CHUNK_ELEMENTS = 1 << 22
"""Largest intermediate of sampled keys, in elements (16 MB in float32: below glibc's
largest mmap threshold, 32 MB, so the chunks reuse heap memory instead of each mapping
and page-faulting fresh memory)."""


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
    memory: Tensor,
    projection: nn.Linear,
    spatial_shapes: list[tuple[int, int]],
    heads: int,
    *,
    border: bool = True,
    onednn: bool = False,
    bfloat16_rows: bool = True,
) -> Tensor:
    """``projection(memory)`` split into heads as gather rows, with or without the border.

    Without gradients, the padded table is built in one pass: the projection's matrix
    product is written straight into the padded layout together with its bias (only the
    borders are zeroed), which saves the bias broadcast, the padding and the concatenation
    copies of the plain formulation; with gradients, the plain (differentiable) one is used.

    Args:
        memory: (B, S, C) tokens.
        projection: the value or key projection (C → C).
        spatial_shapes: (H_l, W_l) per level.
        heads: attention heads M.
        border: `padded_table`'s zero border (see the module docstring); without it the
            table is the projection's rows, (B · S · M, C / M).
        onednn: run the product as a oneDNN inner product where that applies
            (`taptr.model.ops.dense`).
        bfloat16_rows: without the border, inside `bfloat16_products`, keep the rows in
            bfloat16 (keys, whose samples feed scores); False gives float32 rows.

    Returns:
        (B · Σ(H_l + 3)(W_l + 3) · M, C / M), or (B · S · M, C / M) without the border.
    """
    batch, tokens, channels = memory.shape
    differentiable = torch.is_grad_enabled() and (
        memory.requires_grad or projection.weight.requires_grad
    )
    if not border:
        if differentiable:
            return projection(memory).reshape(-1, channels // heads)
        if onednn:
            # inside bfloat16 products the rows stay bfloat16: half the bytes to gather
            keep = bfloat16_rows and bfloat16_mode()
            rows = apply_linear(projection, memory, onednn=True, keep_type=keep)
            return rows.reshape(-1, channels // heads)
        flat = memory.reshape(-1, channels)  # (B·S, C)
        rows = torch.addmm(projection.bias, flat, projection.weight.t())
        return rows.view(-1, channels // heads)
    if differentiable:
        return padded_table(projection(memory).view(batch, tokens, heads, -1), spatial_shapes)
    product = linear(memory, projection.weight, None, onednn=onednn)  # (B, S, C), no bias
    padded_sizes = [(h + 3) * (w + 3) for h, w in spatial_shapes]
    # one fill of the whole table, not four border strips per level: 16 launches fewer
    # per table, for a pass over a few megabytes
    table = memory.new_zeros(batch, sum(padded_sizes), channels)
    start, padded_start = 0, 0
    for (height, width), size in zip(spatial_shapes, padded_sizes, strict=True):
        level = table[:, padded_start : padded_start + size].view(
            batch, height + 3, width + 3, channels
        )
        interior = product[:, start : start + height * width].view(batch, height, width, channels)
        torch.add(interior, projection.bias, out=level[:, 1 : height + 1, 1 : width + 1])
        start, padded_start = start + height * width, padded_start + size
    return table.view(-1, channels // heads)


def interleaved_sizes(spatial_shapes: list[tuple[int, int]], points: int, like: Tensor) -> Tensor:
    """(W_l, H_l) of every level, repeated for its points: (L · P · 2) as x, y pairs.

    Elementwise ops between (..., L · P · 2) rows and this vector run along one contiguous
    axis, where broadcasting a (L, 1, 2) size over (..., L, P, 2) runs an inner loop of two.
    """
    levels = len(spatial_shapes)

    def make() -> Tensor:
        sizes = like.new_tensor([[w, h] for h, w in spatial_shapes])  # (L, 2)
        return sizes.view(levels, 1, 2).expand(levels, points, 2).reshape(-1)

    return kept(("interleaved sizes", tuple(spatial_shapes), points, like.device, like.dtype), make)


def bilinear_corners(
    locations: Tensor,
    spatial_shapes: list[tuple[int, int]],
    scale: Tensor | None = None,
    *,
    border: bool = True,
) -> tuple[Tensor, Tensor]:
    """Rows and weights of the four corners of every location.

    Args:
        locations: (B, Q, M, L, P, 2) locations (x, y) in [0, 1] of each level.
        spatial_shapes: (H_l, W_l) per level.
        scale: optional (B, Q, M, L, P) factor folded into the weights.
        border: rows into a `padded_table` (True), or into a table without the border
            with zero weight on corners outside their level (False).

    Returns:
        rows (B, Q, M, L·P, 4) and weights of the same shape, corners ordered
        (y0 x0, y0 x1, y1 x0, y1 x1).
    """
    batch, _, heads, levels, points, _ = locations.shape
    row_lengths = [w + 3 if border else w for _, w in spatial_shapes]
    level_rows = [(h + 3) * (w + 3) if border else h * w for h, w in spatial_shapes]
    # int32 rows halve the traffic of the index arithmetic while the table fits
    index = torch.int32 if batch * sum(level_rows) * heads < 2**31 else torch.int64
    sizes = interleaved_sizes(spatial_shapes, points, locations)  # (L·P·2)
    pixels = locations.flatten(3) * sizes - 0.5  # (B, Q, M, L·P·2) in each level's pixels
    # beyond one cell outside, every corner is outside: clamp there (bounds the integers)
    pixels = torch.minimum(pixels, sizes).clamp_(min=-1.0)
    corner = pixels.floor()
    frac = (pixels - corner).view(locations.shape)
    fx, fy = frac[..., 0], frac[..., 1]
    gx, gy = 1 - fx, 1 - fy
    if border:
        low = high = corner.to(index).add_(1).view(locations.shape)  # padded coordinates
    else:
        last = sizes - 1
        inside_low = ((corner >= 0) & (corner <= last)).view(locations.shape)
        inside_high = (corner < last).view(locations.shape)  # corner + 1 in [0, size − 1]
        high = torch.minimum(corner + 1, last).to(index).view(locations.shape)
        low = torch.minimum(corner.clamp_(min=0.0), last).to(index).view(locations.shape)
        gx, fx = gx * inside_low[..., 0], fx * inside_high[..., 0]
        gy, fy = gy * inside_low[..., 1], fy * inside_high[..., 1]
    device = locations.device
    key = ("corners", tuple(spatial_shapes), border, batch, heads, device, index)
    starts = [sum(level_rows[:i]) * heads for i in range(levels)]
    # table row of (image b, token s, head m) is (b·S_t + s)·M + m: per level, the first
    # row of each image and head, and the rows of one feature row (lengths · M)
    line_rows = kept(
        (*key, "lines"),
        lambda: torch.tensor([n * heads for n in row_lengths], device=device, dtype=index).view(
            levels, 1
        ),
    )
    image_head = kept(
        (*key, "base"), lambda: first_rows(batch, heads, starts, level_rows, index, device)
    )
    top_left = image_head + low[..., 1] * line_rows + low[..., 0] * heads
    # corners are written into strided slices: stacking them costs several times more
    rows = top_left.new_empty(*top_left.shape, 4)  # (B, Q, M, L, P, 4)
    rows[..., 0] = top_left
    if border:  # the other corners are the next cell and row, inside the border
        torch.add(top_left, heads, out=rows[..., 1])
        torch.add(top_left, line_rows, out=rows[..., 2])
        torch.add(rows[..., 2], heads, out=rows[..., 3])
    else:  # clamped cells: a far corner outside the level repeats the near one (weight 0)
        right = (high[..., 0] - low[..., 0]) * heads
        torch.add(top_left, right, out=rows[..., 1])
        below = image_head + high[..., 1] * line_rows + low[..., 0] * heads
        rows[..., 2] = below
        torch.add(below, right, out=rows[..., 3])
    weights = _corner_weights(fx, fy, gx, gy, scale)
    shape = (*locations.shape[:3], levels * points, 4)
    return rows.view(shape), weights.view(shape)


def first_rows(
    batch: int,
    heads: int,
    starts: list[int],
    level_rows: list[int],
    index: torch.dtype,
    device: torch.device,
) -> Tensor:
    """(B, 1, M, L, 1) table row of each image, head and level's first token.

    ``starts`` are each level's first row in an image's table (its first token times M),
    ``level_rows`` the tokens of each level.
    """
    images = torch.arange(batch, device=device, dtype=index) * (sum(level_rows) * heads)
    head = torch.arange(heads, device=device, dtype=index)
    level = torch.tensor(starts, device=device, dtype=index)
    rows = images.view(batch, 1, 1) + head.view(1, heads, 1) + level.view(1, 1, -1)
    return rows.view(batch, 1, heads, len(starts), 1)


def _corner_weights(fx: Tensor, fy: Tensor, gx: Tensor, gy: Tensor, scale: Tensor | None) -> Tensor:
    """The four bilinear products (y0 x0, y0 x1, y1 x0, y1 x1), times ``scale``: (..., 4)."""
    if scale is not None:
        fy, gy = fy * scale, gy * scale
    if torch.is_grad_enabled() and (fx.requires_grad or fy.requires_grad):
        return torch.stack((gy * gx, gy * fx, fy * gx, fy * fx), -1)  # out= has no autograd
    weights = fx.new_empty(*fx.shape, 4)
    torch.mul(gy, gx, out=weights[..., 0])
    torch.mul(gy, fx, out=weights[..., 1])
    torch.mul(fy, gx, out=weights[..., 2])
    torch.mul(fy, fx, out=weights[..., 3])
    return weights


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
    *,
    border: bool = True,
) -> tuple[Tensor, Tensor]:
    """Key-aware deformable attention; `key_aware_ms_deform_attn` on gather tables.

    Args:
        queries: (B, Q, M, D) projected queries.
        key_table: (B · S_t · M, D) keys, see `padded_table` / `projected_table`.
        value_table: (B · S_t · M, D) values.
        spatial_shapes: (H_l, W_l) per level.
        locations: (B, Q, M, L, P, 2) in [0, 1].
        border: whether the tables have the zero border (`bilinear_corners`).

    Returns:
        output (B, Q, M·D) and pre-softmax logits (B, Q, M, L, P).
    """
    rows, corner_weights = bilinear_corners(locations, spatial_shapes, border=border)
    output, logits = key_aware_from_corners(queries, key_table, value_table, rows, corner_weights)
    return output, logits.view(locations.shape[:-1])


def key_aware_from_corners(
    queries: Tensor, key_table: Tensor, value_table: Tensor, rows: Tensor, corner_weights: Tensor
) -> tuple[Tensor, Tensor]:
    """`gather_key_aware_attn` from the locations' corners (`bilinear_corners`).

    Args:
        queries: (B, Q, M, D) projected queries.
        key_table: gather rows of the keys, (R, D).
        value_table: gather rows of the values, (R, D).
        rows: (B, Q, M, L·P, 4) corner rows into both tables.
        corner_weights: (B, Q, M, L·P, 4) their bilinear weights.

    Returns:
        output (B, Q, M·D) and pre-softmax logits (B, Q, M, L·P).
    """
    batch, num_queries, heads, channels = queries.shape
    samples = rows.shape[3]
    # sampled keys are (B, Q, M, L·P, D): bound their memory by taking queries in chunks
    chunk = max(1, CHUNK_ELEMENTS // (batch * heads * samples * channels))
    # a bfloat16 table (`taptr.model.frame_tables`) gives bfloat16 samples: the scores,
    # their softmax and the output are float32 all the same
    parts = [
        torch.einsum(
            "bqmd,bqmjd->bqmj",
            queries[:, start : start + chunk],
            gather_sum(
                key_table, rows[:, start : start + chunk], corner_weights[:, start : start + chunk]
            ).to(queries.dtype),
        )
        for start in range(0, num_queries, chunk)
    ]
    logits = (parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)) / channels**0.5
    combined = corner_weights * logits.softmax(-1).unsqueeze(-1)  # (B, Q, M, L·P, 4)
    out = gather_sum(value_table, rows.flatten(-2), combined.flatten(-2)).to(queries.dtype)
    return out.view(batch, num_queries, heads * channels), logits
