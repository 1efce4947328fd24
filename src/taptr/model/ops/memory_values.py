"""Deformable values projected after sampling: no value table for a few hundred points.

A decoder layer's output of head m is Σ_r w_r · (W_m · x_r + b_m) over the rows r its
points sample (four bilinear corners of every location, each weight folding in the
attention), with x_r a memory token and (W_m, b_m) the head's slice of the value
projection. A linear projection commutes with the weighted sum:

    Σ_r w_r · (W_m · x_r + b_m) = W_m · (Σ_r w_r · x_r) + b_m · Σ_r w_r

so the memory is sampled first, C channels a row, and each point and head projects one
sampled vector: N · M · C · D products instead of S · C · C for the table of every
token. The weights of corners outside their level are zero (`gather.bilinear_corners`
without the border), which is the zero padding of ``grid_sample``: such a corner adds
neither its token nor the bias, hence ``b_m · Σ_r w_r`` and not ``b_m``.

Reading C channels a row instead of D costs more per sample: `values_after_sampling`
chooses, per shape, whichever of the two costs less (the same choice for every frame of
a shape, so that a captured step never asks the data).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from taptr.model.ops.gather import gather_sum

GATHERED_ELEMENT_COST = 6.0
"""One float read by a row gather, in multiply-adds of the table's large product: a gather
reads scattered rows where the product streams its operands through the caches, so an
element gathered costs several multiply-adds (the ratio measured: docs/BENCHMARKS_LOG.md)."""


class MemoryValues(NamedTuple):
    """The values of a layer as its memory and projection, projected after sampling.

    Attributes:
        memory: (B, S, C) the frame's tokens, levels flattened row-major.
        projection: the value projection (C → C, heads of D = C / M channels).
    """

    memory: Tensor
    projection: nn.Linear


def values_after_sampling(
    points: int, samples: int, tokens: int, channels: int, heads: int
) -> bool:
    """Whether sampling the memory then projecting costs less than the value table.

    Args:
        points: query points N (of all images).
        samples: locations per point and head, L · P (four corners each).
        tokens: memory tokens S (of all images).
        channels: C.
        heads: M.
    """
    sampled = points * heads * samples * 4 * channels * GATHERED_ELEMENT_COST
    projected = points * channels * channels  # one vector per point and head, D each
    return sampled + projected < tokens * channels * channels


def sample_memory_values(values: MemoryValues, rows: Tensor, weights: Tensor, heads: int) -> Tensor:
    """Σ_r weights · value_projection(memory)[rows] without projecting the memory.

    Args:
        values: the memory and the value projection.
        rows: (B, Q, M, R) rows into the (B · S · M, D) head rows of the value table
            (token-major, heads fastest), R sampled rows per point and head.
        weights: (B, Q, M, R) their weights, zero for corners outside their level.
        heads: M.

    Returns:
        (B, Q, M, D), float32 (the memory's type).
    """
    memory, projection = values
    channels = memory.shape[-1]
    # head row (b·S + s)·M + m → memory row b·S + s: the same token, every channel
    tokens = torch.div(rows, heads, rounding_mode="floor")
    sampled = gather_sum(memory.reshape(-1, channels), tokens, weights)  # (B, Q, M, C)
    weight = projection.weight.view(heads, channels // heads, channels)  # (M, D, C)
    # per head: (B·Q, C) × (C, D); einsum orders the batch over heads for one bmm
    out = torch.einsum("bqmc,mdc->bqmd", sampled, weight.to(sampled.dtype))
    bias = projection.bias.view(heads, -1).to(out.dtype)  # (M, D)
    return torch.addcmul(out, weights.sum(-1, keepdim=True).to(out.dtype), bias)
