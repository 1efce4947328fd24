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
from taptr.model.ops.gather import CHUNK_ELEMENTS, bilinear_corners, gather_sum, projected_table
from taptr.model.ops.ms_deform_attn import sample_each_level


def patch_steps(patch: int, like: Tensor) -> Tensor:
    """(K·K, 2) steps (dx, dy) in feature pixels, index a·K + b = (offsets[a], offsets[b]).

    The first axis is x, as in the official ``meshgrid(offsets, offsets)`` ('ij').
    """
    offsets = torch.arange(patch, dtype=like.dtype, device=like.device) - (patch - 1) / 2
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


def sample_key_patches(
    kernel: str,
    memory: Tensor,
    key_proj: nn.Linear,
    spatial_shapes: list[tuple[int, int]],
    patches: Tensor,
    heads: int,
    *,
    onednn: bool = False,
) -> Tensor:
    """Bilinear samples of the projected keys at patch locations.

    Args:
        kernel: ``grid_sample`` or ``gather``.
        memory: (B, S, C) tokens of one frame per batch entry.
        key_proj: the key projection.
        spatial_shapes: (H_l, W_l) per level.
        patches: (B, Q, M, L, P', 2) locations in [0, 1] (`patch_locations`).
        heads: M.
        onednn: project through oneDNN where that applies.

    Returns:
        (B, Q, M, L·P', D) per-head key samples, zero outside each level.
    """
    batch, queries = patches.shape[:2]
    channels = memory.shape[-1] // heads
    if kernel == "gather":
        table = projected_table(
            memory, key_proj, spatial_shapes, heads, border=False, onednn=onednn
        )
        per_query = heads * patches.shape[3] * patches.shape[4] * channels * batch
        chunk = max(1, CHUNK_ELEMENTS // per_query)
        parts = []
        for start in range(0, queries, chunk):
            rows, weights = bilinear_corners(
                patches[:, start : start + chunk], spatial_shapes, border=False
            )
            parts.append(gather_sum(table, rows, weights))  # (B, q, M, L·P', D)
        return torch.cat(parts, dim=1)
    keys = apply_linear(key_proj, memory, onednn=onednn).view(*memory.shape[:2], heads, channels)
    levels = list(sample_each_level(keys, spatial_shapes, patches))  # (B·M, D, Q, P') each
    sampled = torch.cat(levels, dim=-1)  # (B·M, D, Q, L·P')
    return sampled.view(batch, heads, channels, queries, -1).permute(0, 3, 1, 4, 2)
