"""Deformable-attention kernels, all pure PyTorch, selectable per model.

``grid_sample`` is the reference formulation (Deformable DETR's, what the official code
computes); ``gather`` computes the same sums as weighted row gathers and is the default
(several times faster on CPU, no layout copies). `deform_attn` and `key_aware_attn` take
the memory and its projections and run the chosen kernel; `set_kernel` switches a model.
"""

from __future__ import annotations

from torch import Tensor, nn

from taptr.model.ops.gather import (
    gather_deform_attn,
    gather_key_aware_attn,
    padded_table,
    projected_table,
)
from taptr.model.ops.ms_deform_attn import (
    key_aware_ms_deform_attn,
    level_start_index,
    ms_deform_attn,
    sample_levels,
)

KERNELS = ("grid_sample", "gather")


def deform_attn(
    kernel: str,
    memory: Tensor,
    value_proj: nn.Linear,
    spatial_shapes: list[tuple[int, int]],
    locations: Tensor,
    weights: Tensor,
) -> Tensor:
    """Standard deformable attention over projected memory.

    Args:
        kernel: ``grid_sample`` or ``gather``.
        memory: (B, S, C) tokens.
        value_proj: the value projection.
        spatial_shapes: (H_l, W_l) per level.
        locations: (B, Q, M, L, P, 2) in [0, 1].
        weights: (B, Q, M, L, P) softmaxed over (L, P).

    Returns:
        (B, Q, C).
    """
    heads = locations.shape[2]
    if kernel == "gather":
        table = projected_table(memory, value_proj, spatial_shapes, heads)
        return gather_deform_attn(table, spatial_shapes, locations, weights)
    values = value_proj(memory).view(*memory.shape[:2], heads, -1)  # (B, S, M, D)
    return ms_deform_attn(values, spatial_shapes, locations, weights)


def key_aware_attn(
    kernel: str,
    queries: Tensor,
    memory: Tensor,
    key_proj: nn.Linear,
    value_proj: nn.Linear,
    spatial_shapes: list[tuple[int, int]],
    locations: Tensor,
) -> tuple[Tensor, Tensor]:
    """Key-aware deformable attention over projected memory.

    Args:
        kernel: ``grid_sample`` or ``gather``.
        queries: (B, Q, M, D) projected queries.
        memory: (B, S, C) tokens.
        key_proj: the key projection.
        value_proj: the value projection.
        spatial_shapes: (H_l, W_l) per level.
        locations: (B, Q, M, L, P, 2) in [0, 1].

    Returns:
        output (B, Q, C) and pre-softmax logits (B, Q, M, L, P).
    """
    heads = locations.shape[2]
    if kernel == "gather":
        keys = projected_table(memory, key_proj, spatial_shapes, heads)
        values = projected_table(memory, value_proj, spatial_shapes, heads)
        return gather_key_aware_attn(queries, keys, values, spatial_shapes, locations)
    shape = (*memory.shape[:2], heads, -1)  # (B, S, M, D)
    return key_aware_ms_deform_attn(
        queries,
        key_proj(memory).view(shape),
        value_proj(memory).view(shape),
        spatial_shapes,
        locations,
    )


def set_kernel(model: nn.Module, name: str) -> nn.Module:
    """Makes every deformable attention of ``model`` use kernel ``name``; returns the model."""
    if name not in KERNELS:
        raise ValueError(f"unknown kernel {name!r}; choose from {', '.join(KERNELS)}")
    for module in model.modules():
        if hasattr(module, "kernel") and hasattr(module, "sampling_offsets"):
            module.kernel = name
    return model


__all__ = [
    "KERNELS",
    "deform_attn",
    "gather_deform_attn",
    "gather_key_aware_attn",
    "key_aware_attn",
    "key_aware_ms_deform_attn",
    "level_start_index",
    "ms_deform_attn",
    "padded_table",
    "projected_table",
    "sample_levels",
    "set_kernel",
]
