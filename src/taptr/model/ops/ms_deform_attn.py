"""Multi-scale deformable sampling in pure PyTorch, built on ``grid_sample``.

Each head reads its own channels of every feature level at a few sampled locations. The
locations are normalised to [0, 1] per level with the align_corners=False convention
(pixel coordinate = location · size − 0.5) and zero padding outside the map, which is what
the official CUDA kernel computes.
"""

from __future__ import annotations

from collections.abc import Iterator

import torch
import torch.nn.functional as F
from torch import Tensor


def level_start_index(spatial_shapes: list[tuple[int, int]]) -> list[int]:
    """Offsets of each level in the flattened token axis S."""
    starts = [0]
    for height, width in spatial_shapes[:-1]:
        starts.append(starts[-1] + height * width)
    return starts


def sample_each_level(
    values: Tensor, spatial_shapes: list[tuple[int, int]], locations: Tensor
) -> Iterator[Tensor]:
    """Bilinearly samples per-head values of each level at the given locations, level by level.

    Args:
        values: (B, S, M, D) tokens of all levels, flattened row-major per level.
        spatial_shapes: (H_l, W_l) of the L levels, summing to S tokens.
        locations: (B, Q, M, L, P, 2) sampling locations (x, y) in [0, 1] per level.

    Yields:
        (B·M, D, Q, P) sampled values of each level in turn.
    """
    batch, _, heads, channels = values.shape
    queries, points = locations.shape[1], locations.shape[4]
    grids = 2 * locations - 1
    # split, not slices: the backward of a split concatenates the levels' gradients, where
    # each slice's backward would fill a zero tensor of the whole memory
    levels = values.split([height * width for height, width in spatial_shapes], dim=1)
    for level, (level_values, (height, width)) in enumerate(
        zip(levels, spatial_shapes, strict=True)
    ):  # level_values: (B, H·W, M, D)
        level_values = level_values.permute(0, 2, 3, 1).reshape(
            batch * heads, channels, height, width
        )  # (B·M, D, H, W)
        grid = (
            grids[:, :, :, level].transpose(1, 2).reshape(batch * heads, queries, points, 2)
        )  # (B·M, Q, P, 2)
        yield F.grid_sample(
            level_values, grid, mode="bilinear", padding_mode="zeros", align_corners=False
        )  # (B·M, D, Q, P)


def weighted_sum(sampled: list[Tensor], weights: Tensor) -> Tensor:
    """Combines each level's sampled values with per-head attention weights.

    Summed level by level, so the levels are never stacked into one (B·M, D, Q, L·P) copy.

    Args:
        sampled: L tensors (B·M, D, Q, P) from `sample_each_level`.
        weights: (B, Q, M, L·P), summing to one over the last axis.

    Returns:
        (B, Q, M·D), heads concatenated.
    """
    batch, queries, heads, _ = weights.shape
    channels, points = sampled[0].shape[1], sampled[0].shape[-1]
    weights = weights.transpose(1, 2).reshape(batch * heads, 1, queries, -1)  # (B·M, 1, Q, L·P)
    level_weights = weights.split(points, dim=-1)  # (B·M, 1, Q, P) per level
    output = sum(
        (level * weight).sum(-1) for level, weight in zip(sampled, level_weights, strict=True)
    )  # (B·M, D, Q)
    return output.view(batch, heads * channels, queries).transpose(1, 2)


def ms_deform_attn(
    values: Tensor, spatial_shapes: list[tuple[int, int]], locations: Tensor, weights: Tensor
) -> Tensor:
    """Standard multi-scale deformable attention (Deformable DETR's core).

    Args:
        values: (B, S, M, D).
        spatial_shapes: (H_l, W_l) per level.
        locations: (B, Q, M, L, P, 2) in [0, 1].
        weights: (B, Q, M, L, P) attention weights, softmaxed over (L, P) per head.

    Returns:
        (B, Q, M·D).
    """
    sampled = list(sample_each_level(values, spatial_shapes, locations))
    return weighted_sum(sampled, weights.flatten(-2))


def key_aware_ms_deform_attn(
    queries: Tensor,
    keys: Tensor,
    values: Tensor,
    spatial_shapes: list[tuple[int, int]],
    locations: Tensor,
) -> tuple[Tensor, Tensor]:
    """Key-aware deformable attention: weights from query · sampled-key dot products.

    Keys and values are sampled at the same locations in one ``grid_sample`` call per
    level; each head's logits are scaled by 1/√D and softmaxed over its L·P samples.

    Args:
        queries: (B, Q, M, D) projected queries.
        keys: (B, S, M, D) projected keys.
        values: (B, S, M, D) projected values.
        spatial_shapes: (H_l, W_l) per level.
        locations: (B, Q, M, L, P, 2) in [0, 1].

    Returns:
        output (B, Q, M·D) and the pre-softmax logits (B, Q, M, L, P).
    """
    batch, num_queries, heads, channels = queries.shape
    levels, points = locations.shape[3:5]
    sampled = sample_each_level(torch.cat((keys, values), dim=-1), spatial_shapes, locations)
    pairs = [level.split(channels, dim=1) for level in sampled]  # (B·M, D, Q, P) key, value
    q = queries.permute(0, 2, 3, 1).reshape(batch * heads, channels, num_queries, 1)
    logits = torch.cat([(q * key).sum(1) for key, _ in pairs], -1)  # (B·M, Q, L·P)
    logits = logits / channels**0.5
    logits = logits.view(batch, heads, num_queries, levels * points).transpose(1, 2)
    output = weighted_sum([value for _, value in pairs], logits.softmax(-1))
    return output, logits.view(batch, num_queries, heads, levels, points)
