"""Sine position encodings: of feature-map cells (encoder) and of point positions (decoder).

Both use the official temperature of 10 (not the usual 10000) and interleave sin and cos:
channel k of a coordinate's block is ``sin(c / d_k)`` for even k and ``cos(c / d_k)`` for
odd k with ``d_k = temperature ** (2 * (k // 2) / n)``. The frequency table is float32, as
in the official code, and cast to the input dtype afterwards.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from taptr.model.ops.constants import kept


def _frequencies(channels: int, temperature: float, device: torch.device) -> Tensor:
    """(channels,) float32 d_k, made once per device (`kept`)."""

    def make() -> Tensor:
        k = torch.arange(channels, dtype=torch.float32, device=device)
        return temperature ** (2 * torch.div(k, 2, rounding_mode="floor") / channels)

    return kept(("sine frequencies", channels, temperature, device), make)


def _interleave(angles: Tensor) -> Tensor:
    """(..., n) angles → (..., n) with sin on even and cos on odd channels."""
    return torch.stack((angles[..., 0::2].sin(), angles[..., 1::2].cos()), dim=-1).flatten(-2)


def sine_embedding(coords: Tensor, channels: int, temperature: float) -> Tensor:
    """Sine embedding of each coordinate, concatenated in the given coordinate order.

    Args:
        coords: (..., K) values in [0, 1] (scaled by 2π inside), or displacements.
        channels: channels per coordinate (C / 2 in the model).
        temperature: frequency temperature (10 in TAPTRv2).

    Returns:
        (..., K · channels).
    """
    freqs = _frequencies(channels, temperature, coords.device)
    if coords.dtype != freqs.dtype:
        freqs = freqs.to(coords.dtype)
    angles = coords.unsqueeze(-1) * (2 * math.pi) / freqs  # (..., K, channels)
    return _interleave(angles).flatten(-2)


def point_embedding(positions: Tensor, channels: int, temperature: float) -> Tensor:
    """Embedding of 2-d (x, y) or 4-d (x, y, w, h) positions in the official (y, x, ...) order.

    Args:
        positions: (..., 2) or (..., 4), x first.
        channels: channels per coordinate.
        temperature: frequency temperature.

    Returns:
        (..., 2 · channels) or (..., 4 · channels), the y block first.
    """
    order = [1, 0] + list(range(2, positions.shape[-1]))
    return sine_embedding(positions[..., order], channels, temperature)


def feature_map_encoding(
    height: int, width: int, channels: int, temperature: float, device: torch.device
) -> Tensor:
    """Encoding of every cell of an H×W map, computed in float32.

    Rows and columns are counted from 1 and normalised by ``size + 1e-6`` before the 2π
    scaling, as in the official ``PositionEmbeddingSineHW``.

    Returns:
        (H·W, 2 · channels): the y block then the x block, cells in row-major order.
    """
    eps = 1e-6
    rows = torch.arange(1, height + 1, dtype=torch.float32, device=device) / (height + eps)
    cols = torch.arange(1, width + 1, dtype=torch.float32, device=device) / (width + eps)
    freqs = _frequencies(channels, temperature, device)
    y = _interleave(rows[:, None] * (2 * math.pi) / freqs)  # (H, channels)
    x = _interleave(cols[:, None] * (2 * math.pi) / freqs)  # (W, channels)
    grid = torch.cat(
        (y[:, None, :].expand(height, width, channels), x[None].expand(height, width, channels)),
        dim=-1,
    )  # (H, W, 2·channels)
    return grid.reshape(height * width, 2 * channels)
