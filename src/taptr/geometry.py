"""The single home of coordinate conventions.

Pixel convention: integer coordinates are pixel centres; pixel (0, 0) is the centre of the
top-left pixel. Inside the model a position is normalised as ``x / (W - 1), y / (H - 1)``
(so 0 and 1 are the centres of the first and last pixel), and the decoder carries it in
inverse-sigmoid ("logit") space. TAP-Vid raster coordinates are converted only by the
evaluation adapter.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

INVERSE_SIGMOID_EPS = 1e-3
"""The official clamp; also bounds every updated position to ≈[0.000999, 0.999001]."""


def inverse_sigmoid(x: Tensor, eps: float = INVERSE_SIGMOID_EPS) -> Tensor:
    """Logit with the official clamp: ``log(max(x, eps) / max(1 - x, eps))`` on x ∈ [0, 1]."""
    x = x.clamp(min=0, max=1)
    return torch.log(x.clamp(min=eps) / (1 - x).clamp(min=eps))


def clamp_to_unit(x: Tensor) -> Tensor:
    """The official sigmoid∘inverse_sigmoid round trip, which keeps x inside the eps clamp."""
    return inverse_sigmoid(x).sigmoid()


def pixels_to_normalized(points: Tensor, height: int, width: int) -> Tensor:
    """Maps (x, y) pixels (centres at integers) to the model's ``/(W-1), /(H-1)`` units.

    Args:
        points: (..., 2) as (x, y) in pixels.
        height: image height H in pixels.
        width: image width W in pixels.

    Returns:
        (..., 2) normalised (x, y); 0 and 1 are the centres of the first and last pixel.
    """
    scale = points.new_tensor([max(width - 1, 1), max(height - 1, 1)])
    return points / scale


def normalized_to_pixels(points: Tensor, height: int, width: int) -> Tensor:
    """Inverse of `pixels_to_normalized`; (..., 2) normalised (x, y) to pixels."""
    scale = points.new_tensor([max(width - 1, 1), max(height - 1, 1)])
    return points * scale


def rescale_pixels(points: Tensor, from_size: tuple[int, int], to_size: tuple[int, int]) -> Tensor:
    """Maps (x, y) pixels between two resolutions of the same image, per axis.

    With pixel centres at integers, the first and last pixel centres map onto each other,
    so the factor is (size_to - 1) / (size_from - 1) on each axis.

    Args:
        points: (..., 2) as (x, y) in pixels of an image of ``from_size``.
        from_size: (height, width) of the source image.
        to_size: (height, width) of the target image.
    """
    normalized = pixels_to_normalized(points, *from_size)
    return normalized_to_pixels(normalized, *to_size)


def sample_at_pixels(feature: Tensor, points: Tensor) -> Tensor:
    """Bilinear samples of a feature map at pixel-centre coordinates, border padding.

    This is the align_corners=True convention: point (0, 0) reads the top-left value and
    (W - 1, H - 1) the bottom-right one exactly; points outside are clamped to the border.

    Args:
        feature: (B, C, H, W) map.
        points: (B, Q, 2) as (x, y) in the map's pixel units (column, row).

    Returns:
        (B, Q, C) samples.
    """
    height, width = feature.shape[-2:]
    scale = points.new_tensor([2.0 / max(width - 1, 1), 2.0 / max(height - 1, 1)])
    grid = (points * scale - 1).unsqueeze(2)  # (B, Q, 1, 2)
    sampled = F.grid_sample(
        feature, grid, mode="bilinear", padding_mode="border", align_corners=True
    )  # (B, C, Q, 1)
    return sampled.squeeze(-1).transpose(1, 2)
