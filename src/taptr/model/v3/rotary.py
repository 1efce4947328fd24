"""The rotary time embedding of TAPTRv3's long-temporal attention.

Each past frame's content is rotated, before the attention's input projection, by angles
proportional to its distance in frames from the frame being decoded: channel pair
(2i, 2i + 1) turns by p · ω_i, with ω_i = 10000^(−2i/C) (the "interleaved" convention of
RoFormer). The query, at distance 0, is not rotated, and values never are. The
frequencies are a stored, non-trainable parameter so that a released checkpoint's own
table (which its EMA may have rounded) is used as it is.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


def default_frequencies(channels: int) -> Tensor:
    """ω_i = 1 / 10000^(2i / C) for i < C / 2, in float32 as the official module makes them."""
    return 1.0 / 10000 ** (torch.arange(0, channels, 2)[: channels // 2].float() / channels)


def rotate_pairs(x: Tensor) -> Tensor:
    """(x_0, x_1, x_2, x_3, ...) → (−x_1, x_0, −x_3, x_2, ...), the quarter turn of each pair."""
    pairs = x.unflatten(-1, (-1, 2))  # (..., C/2, 2)
    return torch.stack((-pairs[..., 1], pairs[..., 0]), dim=-1).flatten(-2)


class RotaryTime(nn.Module):
    """Rotates features by their distance in time.

    Attributes:
        freqs: (C/2,) angular frequency of each channel pair, not trained.

    Shape:
        x (..., H, C), distances (H,) or (..., H) → (..., H, C).
    """

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.freqs = nn.Parameter(default_frequencies(channels), requires_grad=False)

    def forward(self, x: Tensor, distances: Tensor) -> Tensor:
        """Rotates each row of ``x`` by its distance (in frames) times the frequencies."""
        return rotate(x, *self.turns(distances, x.dtype))

    def turns(self, distances: Tensor, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """Cosines and sines (..., H, C) of the angles of ``distances`` (..., H), per channel.

        The angles are formed in the frequencies' dtype and their cosines and sines cast to
        ``dtype``, as the official module computes them.
        """
        angles = distances.to(self.freqs.dtype).unsqueeze(-1) * self.freqs  # (..., H, C/2)
        angles = angles.repeat_interleave(2, dim=-1).to(dtype)  # (..., H, C)
        return angles.cos(), angles.sin()


def rotate(x: Tensor, cos: Tensor, sin: Tensor) -> Tensor:
    """``x`` (..., H, C) turned by the angles whose cosines and sines are given (H, C)."""
    return x * cos + rotate_pairs(x) * sin
