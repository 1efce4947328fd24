"""Deformable-attention kernels, all pure PyTorch, selectable per model.

``grid_sample`` is the reference formulation (Deformable DETR's, what the official code
computes); ``gather`` computes the same sums as weighted row gathers and is the default
(several times faster on CPU, no layout copies). `set_kernel` switches a whole model.
"""

from __future__ import annotations

from torch import nn

from taptr.model.ops.gather import gather_deform_attn, gather_key_aware_attn
from taptr.model.ops.ms_deform_attn import (
    key_aware_ms_deform_attn,
    level_start_index,
    ms_deform_attn,
    sample_levels,
)

KERNELS = {"grid_sample": ms_deform_attn, "gather": gather_deform_attn}
KEY_AWARE_KERNELS = {"grid_sample": key_aware_ms_deform_attn, "gather": gather_key_aware_attn}


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
    "KEY_AWARE_KERNELS",
    "gather_deform_attn",
    "gather_key_aware_attn",
    "key_aware_ms_deform_attn",
    "level_start_index",
    "ms_deform_attn",
    "sample_levels",
    "set_kernel",
]
