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

import torch
from torch import Tensor, nn

from taptr.model.ops.dense import apply_linear
from taptr.model.ops.gather import CHUNK_ELEMENTS, gather_sum, projected_table
from taptr.model.ops.ms_deform_attn import sample_each_level


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


def patch_corners(
    locations: Tensor, spatial_shapes: list[tuple[int, int]], patch: int
) -> tuple[Tensor, Tensor]:
    """Rows and weights of the four corners of every point of every location's patch.

    The same as `taptr.model.ops.gather.bilinear_corners` of `patch_locations` (borderless
    table), computed per axis, K values each, and combined by broadcasting: the floors,
    fractions and clamps of the K² points are those of K columns and K rows.

    Args:
        locations: (B, Q, M, L, P, 2) patch centres (x, y) in [0, 1] of each level.
        spatial_shapes: (H_l, W_l) per level.
        patch: K.

    Returns:
        rows (B, Q, M, L·P·K², 4) into the (B · S · M, D) table and weights of the same
        shape, patch points in (a, b) order, corners (y0 x0, y0 x1, y1 x0, y1 x1).
    """
    batch, _, heads, levels, points, _ = locations.shape
    level_rows = [h * w for h, w in spatial_shapes]
    index = torch.int32 if batch * sum(level_rows) * heads < 2**31 else torch.int64
    sizes = locations.new_tensor([[w, h] for h, w in spatial_shapes]).view(levels, 1, 2, 1)
    spans = locations.new_tensor([[max(w - 1, 1), max(h - 1, 1)] for h, w in spatial_shapes]).view(
        levels, 1, 2, 1
    )
    steps = patch_offsets(patch, locations)  # (K,): the same steps on both axes
    # (B, Q, M, L, P, 2, K): as patch_locations then bilinear_corners compute them
    pixels = (locations[..., None] + steps / spans) * sizes - 0.5
    pixels = torch.minimum(pixels, sizes).clamp_(min=-1.0)
    corner = pixels.floor()
    frac = pixels - corner
    last = sizes - 1
    near = (1 - frac) * ((corner >= 0) & (corner <= last))
    far = frac * (corner < last)
    high = torch.minimum(corner + 1, last).to(index)
    low = torch.minimum(corner.clamp_(min=0.0), last).to(index)
    starts = torch.tensor(
        [sum(level_rows[:i]) for i in range(levels)], device=locations.device, dtype=index
    ).view(levels, 1, 1, 1)
    widths = torch.tensor(
        [w for _, w in spatial_shapes], device=locations.device, dtype=index
    ).view(levels, 1, 1, 1)
    image_head = torch.arange(batch, device=locations.device, dtype=index).view(
        batch, 1, 1, 1, 1, 1, 1
    )
    image_head = image_head * (sum(level_rows) * heads) + torch.arange(
        heads, device=locations.device, dtype=index
    ).view(1, 1, heads, 1, 1, 1, 1)
    columns = torch.stack((low[..., 0, :], high[..., 0, :]), dim=-1) * heads  # (…, K_a, 2_x)
    lines = torch.stack((low[..., 1, :], high[..., 1, :]), dim=-1)  # (…, K_b, 2_y)
    lines = image_head + (starts + lines * widths) * heads
    rows = lines[..., None, :, :, None] + columns[..., :, None, None, :]  # (…, K_a, K_b, 2, 2)
    across = torch.stack((near[..., 0, :], far[..., 0, :]), dim=-1)
    down = torch.stack((near[..., 1, :], far[..., 1, :]), dim=-1)
    weights = down[..., None, :, :, None] * across[..., :, None, None, :]
    shape = (*locations.shape[:3], levels * points * patch * patch, 4)
    return rows.reshape(shape), weights.reshape(shape)


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


def query_chunks(queries: int, per_query: int) -> list[slice]:
    """Slices of queries whose patch samples stay under `CHUNK_ELEMENTS` elements each."""
    step = max(1, CHUNK_ELEMENTS // max(1, per_query))
    return [slice(start, start + step) for start in range(0, queries, step)]
