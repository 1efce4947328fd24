"""Deformable-attention kernels; the pure-PyTorch reference is the only implementation."""

from taptr.model.ops.ms_deform_attn import (
    key_aware_ms_deform_attn,
    level_start_index,
    ms_deform_attn,
    sample_levels,
)

__all__ = ["key_aware_ms_deform_attn", "level_start_index", "ms_deform_attn", "sample_levels"]
