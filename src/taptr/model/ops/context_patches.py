"""Key patches around deformable sampling locations, for TAPTRv3's context-aware attention.

Each sampling location reads a K × K patch of the projected keys, one feature pixel
apart. The official code places the patch with the align-corners formula
u + d / (size − 1) but samples it with ``grid_sample(align_corners=False)`` and zero
padding, the deformable attention's convention: the centre is exactly the value sample,
the neighbours slightly more than a pixel away (size / (size − 1)). `patch_locations`
reproduces that placement; the keys are then sampled like any deformable location, by
``grid_sample`` (the reference) or by the weighted row gathers of
`taptr.model.ops.gather` (``gather``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

import torch
from torch import Tensor, nn

from taptr.model.ops.constants import kept
from taptr.model.ops.dense import apply_linear
from taptr.model.ops.gather import CHUNK_ELEMENTS, first_rows, gather_sum, projected_table
from taptr.model.ops.memory_values import MemoryValues, sample_memory_values
from taptr.model.ops.ms_deform_attn import sample_each_level

if TYPE_CHECKING:
    from taptr.model.execution import Execution


def patch_offsets(patch: int, like: Tensor) -> Tensor:
    """(K,) steps along one axis in feature pixels, centred: (−1, 0, 1) for K = 3."""
    return torch.arange(patch, dtype=like.dtype, device=like.device) - (patch - 1) / 2


def patch_steps(patch: int, like: Tensor) -> Tensor:
    """(K·K, 2) steps (dx, dy) in feature pixels, index a·K + b = (offsets[a], offsets[b]).

    The first axis is x, as in the official ``meshgrid(offsets, offsets)`` ('ij').
    """
    offsets = patch_offsets(patch, like)
    dx, dy = torch.meshgrid(offsets, offsets, indexing="ij")
    return torch.stack((dx, dy), dim=-1).reshape(-1, 2)


def patch_locations(locations: Tensor, spatial_shapes: list[tuple[int, int]], patch: int) -> Tensor:
    """The K × K patch of every location, in the deformable [0, 1] convention.

    Args:
        locations: (B, Q, M, L, P, 2) locations (x, y) in [0, 1] of each level.
        spatial_shapes: (H_l, W_l) per level.
        patch: K.

    Returns:
        (B, Q, M, L, P·K·K, 2), each location's patch in (a, b) order.
    """
    steps = patch_steps(patch, locations)  # (K·K, 2)
    # one step is 1 / (size − 1): a single-pixel level (where the official code divides
    # by zero) gets steps of a whole level instead
    spans = locations.new_tensor([[max(w - 1, 1), max(h - 1, 1)] for h, w in spatial_shapes])
    moved = locations.unsqueeze(-2) + steps / spans[:, None, None, :]  # (B, Q, M, L, P, K², 2)
    return moved.flatten(4, 5)


def key_table(
    kernel: str,
    memory: Tensor,
    key_proj: nn.Linear,
    spatial_shapes: list[tuple[int, int]],
    heads: int,
    *,
    onednn: bool = False,
) -> Tensor:
    """The projected keys in the layout ``kernel`` samples (`sample_key_patches`).

    Args:
        kernel: ``grid_sample`` or ``gather``.
        memory: (B, S, C) tokens of one frame per batch entry.
        key_proj: the key projection.
        spatial_shapes: (H_l, W_l) per level.
        heads: M.
        onednn: project through oneDNN where that applies.

    Returns:
        ``gather``: borderless gather rows (B · S · M, D); ``grid_sample``: (B, S, M, D).
    """
    if kernel == "gather":
        return projected_table(memory, key_proj, spatial_shapes, heads, border=False, onednn=onednn)
    keys = apply_linear(key_proj, memory, onednn=onednn)
    return keys.view(*memory.shape[:2], heads, -1)


class _PatchTables(NamedTuple):
    """`patch_corners`' constants of one shape, laid out (L, axis, P, K, corner, n)-wise.

    The last axis n runs over (B, Q, M), so every elementwise pass of `patch_corners`
    broadcasts these over a long contiguous axis; in point order the passes would broadcast
    over inner axes of two and three, too short for a vector loop.
    """

    shift: Tensor  # (L, 2, 1, K, 1): pixel offset of step k from the location's, minus 0.5
    sizes: Tensor  # (L, 2, 1, 1, 1): (W_l, H_l)
    last: Tensor  # (L, 2, 1, 1, 1, 1): (W_l − 1, H_l − 1)
    pair: Tensor  # (2, 1): (0, 1), the near and the far cell
    start: Tensor  # (2, 1): (1, 0) and
    sign: Tensor  # (2, 1): (−1, 1): the near weight is 1 − frac, the far one frac
    line_rows: Tensor  # (L, 1, 1, 1, 1): W_l · M, table rows per feature row
    base: Tensor  # (L, 1, 1, 1, n): first table row of each image, head and level


def _patch_tables(
    spatial_shapes: list[tuple[int, int]],
    patch: int,
    batch: int,
    queries: int,
    heads: int,
    like: Tensor,
    index: torch.dtype,
) -> _PatchTables:
    """The constants of `patch_corners`, made once per shape (`kept`)."""
    levels = len(spatial_shapes)
    key = ("patch", tuple(spatial_shapes), patch, batch, queries, heads, like.device, like.dtype)
    key = (*key, index)
    sizes = [[float(w), float(h)] for h, w in spatial_shapes]
    steps = [k - (patch - 1) / 2 for k in range(patch)]
    # one step is 1 / (size − 1) of a level (the official placement, module docstring):
    # a single-pixel level, where the official code divides by zero, takes whole levels
    shift = [
        [[s / max(size - 1, 1) * size - 0.5 for s in steps] for size in level] for level in sizes
    ]
    level_rows = [h * w for h, w in spatial_shapes]
    starts = [sum(level_rows[:i]) * heads for i in range(levels)]

    def floats(name: str, values: object, *shape: int) -> Tensor:
        make = lambda: torch.tensor(values, dtype=like.dtype, device=like.device).view(*shape)  # noqa: E731
        return kept((*key, name), make)

    def base() -> Tensor:
        rows = first_rows(batch, heads, starts, level_rows, index, like.device)  # (B, 1, M, L, 1)
        rows = rows.view(batch, 1, heads, levels).expand(batch, queries, heads, levels)
        return rows.permute(3, 0, 1, 2).reshape(levels, 1, 1, 1, -1)  # (L, 1, 1, 1, B·Q·M)

    line_rows = [w * heads for _, w in spatial_shapes]
    return _PatchTables(
        shift=floats("shift", shift, levels, 2, 1, patch, 1),
        sizes=floats("sizes", sizes, levels, 2, 1, 1, 1),
        last=floats("last", [[w - 1, h - 1] for w, h in sizes], levels, 2, 1, 1, 1, 1),
        pair=floats("pair", [0.0, 1.0], 2, 1),
        start=floats("start", [1.0, 0.0], 2, 1),
        sign=floats("sign", [-1.0, 1.0], 2, 1),
        line_rows=kept(
            (*key, "lines"),
            lambda: torch.tensor(line_rows, device=like.device, dtype=index).view(
                levels, 1, 1, 1, 1
            ),
        ),
        base=kept((*key, "base"), base),
    )


def patch_corners(
    locations: Tensor, spatial_shapes: list[tuple[int, int]], patch: int
) -> tuple[Tensor, Tensor]:
    """Rows and weights of the four corners of every point of every location's patch.

    The same as `taptr.model.ops.gather.bilinear_corners` of `patch_locations` (borderless
    table), computed per axis, K values each, and combined by broadcasting: the floors,
    fractions and clamps of the K² points are those of K columns and K rows, and the near
    and far corner of each are one more axis of two. The work runs with the points,
    (B, Q, M), on the last axis (`_PatchTables`); one transposing copy each of the rows
    and the weights puts them back in point order at the end.

    Args:
        locations: (B, Q, M, L, P, 2) patch centres (x, y) in [0, 1] of each level.
        spatial_shapes: (H_l, W_l) per level.
        patch: K.

    Returns:
        rows (B, Q, M, L·P·K², 4) into the (B · S · M, D) table and weights of the same
        shape, patch points in (a, b) order, corners (y0 x0, y0 x1, y1 x0, y1 x1).
    """
    batch, queries, heads, levels, points, _ = locations.shape
    total = sum(h * w for h, w in spatial_shapes)
    index = torch.int32 if batch * total * heads < 2**31 else torch.int64
    tables = _patch_tables(spatial_shapes, patch, batch, queries, heads, locations, index)
    # (L, 2, P, 1, n), n = B·Q·M: the points last, contiguous (a view would leave them
    # strided, and every result after it in that order)
    along = locations.permute(3, 5, 4, 0, 1, 2).contiguous().view(levels, 2, points, 1, -1)
    # (L, 2, P, K, n): pixel of each step on each axis, as patch_locations and
    # bilinear_corners place it; beyond one cell outside, every corner is outside
    pixels = torch.addcmul(tables.shift, along, tables.sizes)
    pixels = torch.minimum(pixels, tables.sizes).clamp_(min=-1.0)
    corner = pixels.floor()
    frac = (pixels - corner).unsqueeze(4)  # (L, 2, P, K, 1, n)
    corners = corner.unsqueeze(4) + tables.pair  # (L, 2, P, K, 2, n): near and far cell
    # near: 1 − frac, far: frac; zero where the cell is outside its level
    weights = torch.addcmul(tables.start, frac, tables.sign)
    weights = weights * ((corners >= 0) & (corners <= tables.last))
    cells = torch.minimum(corners.clamp_(min=0.0), tables.last).to(index)
    columns = cells[:, 0] * heads  # (L, P, K_a, 2_x, n)
    lines = torch.addcmul(tables.base, cells[:, 1], tables.line_rows)  # (L, P, K_b, 2_y, n)
    rows = lines[:, :, None, :, :, None] + columns[:, :, :, None, None, :]  # (L, P, a, b, y, x, n)
    weights = weights[:, 1, :, None, :, :, None] * weights[:, 0, :, :, None, None, :]
    shape = (batch, queries, heads, levels * points * patch * patch, 4)
    # (n, L, P, a, b, y, x): back in point order, one copy each (the row gathers, and the
    # patch centres' slice, read them in that order)
    rows = rows.movedim(-1, 0).reshape(shape).contiguous()
    return rows, weights.movedim(-1, 0).reshape(shape).contiguous()


def sample_key_patches(
    kernel: str,
    keys: Tensor,
    spatial_shapes: list[tuple[int, int]],
    locations: Tensor,
    patch: int,
) -> Tensor:
    """Bilinear samples of the projected keys on each location's patch, zero outside levels.

    Args:
        kernel: ``grid_sample`` or ``gather``, the one ``keys`` was made for.
        keys: `key_table`'s output.
        spatial_shapes: (H_l, W_l) per level.
        locations: (B, Q, M, L, P, 2) patch centres in [0, 1].
        patch: K.

    Returns:
        (B, Q, M, L·P·K², D) per-head key samples, patch points in (a, b) order.
    """
    if kernel == "gather":
        rows, weights = patch_corners(locations, spatial_shapes, patch)
        return gather_sum(keys, rows, weights)
    patches = patch_locations(locations, spatial_shapes, patch)
    batch, queries, heads = patches.shape[:3]
    levels = list(sample_each_level(keys, spatial_shapes, patches))  # (B·M, D, Q, P') each
    sampled = torch.cat(levels, dim=-1)  # (B·M, D, Q, L·P')
    return sampled.view(batch, heads, -1, queries, sampled.shape[-1]).permute(0, 3, 1, 4, 2)


def gather_context_attn(
    keys: Tensor,
    values: Tensor | MemoryValues,
    own: Tensor,
    spatial_shapes: list[tuple[int, int]],
    locations: Tensor,
    score: Callable[[Tensor], Tensor],
    block: int | None,
) -> tuple[Tensor, Tensor]:
    """The context-aware attention's logits and output from borderless gather rows.

    The corners of every patch are computed once for all queries; the patch centre is
    the value's sampling location, so its corners (with the attention folded into their
    weights) sample the values in one more gather, without a second corner computation.

    Args:
        keys: (B · S · M, D) borderless key rows (`key_table`).
        values: (B · S · M, D) borderless value rows, or the memory and the value
            projection, projected after sampling (`taptr.model.ops.memory_values`).
        own: (B, Q, M, K², D) each point's projected context.
        spatial_shapes: (H_l, W_l) per level.
        locations: (B, Q, M, L, P, 2) patch centres in [0, 1].
        score: the K⁴ patch products (B, q, M, L·P, K⁴) → logits (B, q, M, L·P).
        block: sampled key elements per block of queries, or None for all at once
            (`query_chunks`).

    Returns:
        output (B, Q, M·D) and logits (B, Q, M, L·P).
    """
    batch, queries, heads, levels, points = locations.shape[:5]
    k2 = own.shape[3]
    patch = math.isqrt(k2)
    rows, weights = patch_corners(locations, spatial_shapes, patch)  # (B, Q, M, L·P·K², 4)
    per_query = batch * heads * levels * points * k2 * own.shape[-1]
    logits = []
    for part in query_chunks(queries, per_query, block):
        sampled = gather_sum(keys, rows[:, part], weights[:, part])  # (B, q, M, L·P·K², D)
        logits.append(score(_patch_products(sampled, own[:, part], levels * points)))
    scores = logits[0] if len(logits) == 1 else torch.cat(logits, dim=1)  # (B, Q, M, L·P)
    centre = (batch, queries, heads, levels * points, k2, 4)
    centre_rows = rows.view(centre)[..., k2 // 2, :]  # (B, Q, M, L·P, 4)
    centre_weights = weights.view(centre)[..., k2 // 2, :] * scores.softmax(-1)[..., None]
    if isinstance(values, MemoryValues):
        out = sample_memory_values(
            values, centre_rows.flatten(-2), centre_weights.flatten(-2), heads
        )
    else:
        out = gather_sum(values, centre_rows.flatten(-2), centre_weights.flatten(-2))
    # out: (B, Q, M, D)
    return out.to(own.dtype).reshape(batch, queries, -1), scores


ACCELERATOR_BLOCK = 1 << 27
"""Sampled key elements per block of queries on accelerators (512 MB in float32): a bound
on memory only; 800 points at TAPTRv3's shapes (37k elements each) take one block."""


def sample_block(execution: Execution, like: Tensor) -> int | None:
    """Sampled key elements per block of queries for ``like``'s device.

    On CPUs the execution's ``sample_block`` (blocks that stay in the caches, or None);
    elsewhere blocks exist only to bound memory (`ACCELERATOR_BLOCK`), each block being a
    few more launches.
    """
    return execution.sample_block if like.device.type == "cpu" else ACCELERATOR_BLOCK


def _patch_products(sampled: Tensor, own: Tensor, locations: int) -> Tensor:
    """All K⁴ dot products of each sampled key patch with the point's own context.

    Args:
        sampled: (B, Q, M, J·K², D) key samples, J locations of K² patch points (x).
        own: (B, Q, M, K², D) the projected context (y).
        locations: J.

    Returns:
        (B, Q, M, J, K²·K²), products in (x, y) order.
    """
    batch, queries, heads, _, channels = own.shape
    k2 = own.shape[3]
    flat_own = own.reshape(-1, k2, channels)  # (B·Q·M, K², D)
    # bfloat16 key rows (`dense.bfloat16_products`) give bfloat16 samples
    keys = sampled.to(own.dtype).view(flat_own.shape[0], -1, channels)  # (B·Q·M, J·K², D)
    # the wide result (K² rows by J·K² columns) keeps the product's kernels busy where the
    # tall one (J·K² rows by only K² columns) would not, even with the reordering copy
    products = torch.bmm(flat_own, keys.transpose(1, 2))  # (B·Q·M, K²_y, J·K²_x)
    products = products.view(batch, queries, heads, k2, locations, k2).permute(0, 1, 2, 4, 5, 3)
    return products.reshape(batch, queries, heads, locations, k2 * k2)


def query_chunks(queries: int, per_query: int, block: int | None = CHUNK_ELEMENTS) -> list[slice]:
    """Slices of queries whose patch samples stay under ``block`` elements each (None: one).

    An exported graph takes one slice: its query count is dynamic.
    """
    if block is None or torch.compiler.is_exporting():
        return [slice(0, queries)]
    step = max(1, block // max(1, per_query))
    return [slice(start, start + step) for start in range(0, queries, step)]
