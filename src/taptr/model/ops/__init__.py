"""The model's computations in more than one formulation, all pure PyTorch.

Which one runs is the model's execution (`taptr.model.execution.Execution`), passed down
to every call; the layer files hold the reference formulations and call these when the
execution asks for the faster ones:

- deformable attention: ``grid_sample`` is the reference (Deformable DETR's, what the
  official code computes, `ms_deform_attn`); ``gather`` computes the same sums as weighted
  row gathers (`gather`, several times faster on CPU, no layout copies). `value_table`
  lays the projected values out for a kernel and `deform_attn` samples them;
  `key_aware_attn` takes the memory and its projections; each runs the kernel it is given;
- TAPTRv3's values sampled from the memory, then projected per point, where that costs
  less than projecting every token (`memory_values`);
- point self-attention on each frame's tracked points only (`point_attention`);
- MLPs in cache-sized row blocks (`row_blocks`);
- linear layers as oneDNN inner products on x86 CPUs (`dense`).
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
from torch import Tensor, nn

from taptr.model.ops.dense import apply_linear
from taptr.model.ops.gather import (
    bilinear_corners,
    gather_deform_attn,
    gather_key_aware_attn,
    key_aware_from_corners,
    padded_table,
    projected_table,
)
from taptr.model.ops.ms_deform_attn import (
    key_aware_ms_deform_attn,
    level_start_index,
    ms_deform_attn,
    sample_each_level,
)
from taptr.model.ops.point_attention import tracked_point_attention
from taptr.model.ops.row_blocks import ROW_BLOCK, blocked_mlp, use_row_blocks

KERNELS = ("grid_sample", "gather")


def value_table(
    kernel: str,
    memory: Tensor,
    value_proj: nn.Linear,
    spatial_shapes: list[tuple[int, int]],
    heads: int,
    *,
    onednn: bool = False,
) -> Tensor:
    """The memory's projected values in the layout ``kernel`` samples (`deform_attn`).

    Args:
        kernel: ``grid_sample`` or ``gather``.
        memory: (B, S, C) tokens.
        value_proj: the value projection.
        spatial_shapes: (H_l, W_l) per level.
        heads: attention heads M.
        onednn: project through oneDNN where that applies (`dense`).

    Returns:
        ``gather``: the bordered table (B · Σ(H_l + 3)(W_l + 3) · M, C / M) of
        `projected_table`; ``grid_sample``: (B, S, M, C / M).
    """
    if kernel == "gather":
        return projected_table(memory, value_proj, spatial_shapes, heads, onednn=onednn)
    values = apply_linear(value_proj, memory, onednn=onednn)
    return values.view(*memory.shape[:2], heads, -1)


def deform_attn(
    kernel: str,
    values: Tensor,
    spatial_shapes: list[tuple[int, int]],
    locations: Tensor,
    weights: Tensor,
) -> Tensor:
    """Standard deformable attention over values laid out by `value_table`.

    Args:
        kernel: ``grid_sample`` or ``gather``, the one ``values`` was made for.
        values: `value_table`'s output.
        spatial_shapes: (H_l, W_l) per level.
        locations: (B, Q, M, L, P, 2) in [0, 1].
        weights: (B, Q, M, L, P) softmaxed over (L, P).

    Returns:
        (B, Q, C).
    """
    if kernel == "gather":
        return gather_deform_attn(values, spatial_shapes, locations, weights)
    return ms_deform_attn(values, spatial_shapes, locations, weights)


def key_aware_attn(
    kernel: str,
    queries: Tensor,
    memory: Tensor,
    key_proj: nn.Linear,
    value_proj: nn.Linear,
    spatial_shapes: list[tuple[int, int]],
    locations: Tensor,
    tables: Iterable[tuple[Tensor, Tensor]] | None = None,
    *,
    onednn: bool = False,
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
        tables: ``gather`` only: each image's (S, C) keys and values, already projected,
            in image order (`taptr.model.frame_tables`), each used before the next is
            taken; the memory is then not read.
        onednn: project through oneDNN where that applies (`dense`).

    Returns:
        output (B, Q, C) and pre-softmax logits (B, Q, M, L, P).
    """
    batch, points, heads, levels, samples = locations.shape[:5]
    if kernel == "gather" and tables is not None:
        channels = queries.shape[-1]
        # every image's corners at once, as rows of one image's table: (1, B·Q, M, L·P, 4)
        flat = locations.flatten(0, 1)[None]
        rows, weights = bilinear_corners(flat, spatial_shapes, border=False)
        per_image = [
            key_aware_from_corners(
                queries[image : image + 1],
                keys.view(-1, channels),  # (S·M, D) gather rows
                values.view(-1, channels),
                rows[:, image * points : (image + 1) * points],
                weights[:, image * points : (image + 1) * points],
            )
            for image, (keys, values) in enumerate(tables)
        ]
        outputs, logits = zip(*per_image, strict=True)
        return torch.cat(outputs), torch.cat(logits).view(batch, points, heads, levels, samples)
    if kernel == "gather":
        # two tables for a few hundred points: no border (the module doc of `gather`)
        keys = projected_table(memory, key_proj, spatial_shapes, heads, border=False, onednn=onednn)
        values = projected_table(
            memory, value_proj, spatial_shapes, heads, border=False, onednn=onednn
        )
        return gather_key_aware_attn(queries, keys, values, spatial_shapes, locations, border=False)
    shape = (*memory.shape[:2], heads, -1)  # (B, S, M, D)
    return key_aware_ms_deform_attn(
        queries,
        apply_linear(key_proj, memory, onednn=onednn).view(shape),
        apply_linear(value_proj, memory, onednn=onednn).view(shape),
        spatial_shapes,
        locations,
    )


__all__ = [
    "KERNELS",
    "ROW_BLOCK",
    "blocked_mlp",
    "deform_attn",
    "gather_deform_attn",
    "gather_key_aware_attn",
    "key_aware_attn",
    "key_aware_ms_deform_attn",
    "level_start_index",
    "ms_deform_attn",
    "padded_table",
    "projected_table",
    "sample_each_level",
    "tracked_point_attention",
    "use_row_blocks",
    "value_table",
]
