"""Coordinate conventions: normalisation, rescaling, sampling at pixel centres, the eps clamp."""

from __future__ import annotations

import math

import pytest
import torch

from taptr.geometry import (
    clamp_to_unit,
    inverse_sigmoid,
    normalized_to_pixels,
    pixels_to_normalized,
    rescale_pixels,
    sample_at_pixels,
)


@pytest.mark.parametrize(("height", "width"), [(64, 64), (48, 96), (480, 854), (1, 7)])
def test_pixel_round_trip(height, width):
    points = torch.tensor([[0.0, 0.0], [width - 1.0, height - 1.0], [3.25, 0.5]])
    normalized = pixels_to_normalized(points, height, width)
    torch.testing.assert_close(normalized_to_pixels(normalized, height, width), points)
    if height > 1:
        torch.testing.assert_close(normalized[1], torch.tensor([1.0, 1.0]))


def test_rescale_maps_first_and_last_pixel_centres():
    points = torch.tensor([[0.0, 0.0], [853.0, 479.0], [426.5, 239.5]])
    scaled = rescale_pixels(points, (480, 854), (512, 512))
    torch.testing.assert_close(scaled, torch.tensor([[0.0, 0.0], [511.0, 511.0], [255.5, 255.5]]))


def test_inverse_sigmoid_clamp():
    assert inverse_sigmoid(torch.tensor(0.5)).item() == 0.0
    assert inverse_sigmoid(torch.tensor(0.0)).item() == pytest.approx(math.log(1e-3 / 1.0))
    assert inverse_sigmoid(torch.tensor(1.5)).item() == pytest.approx(math.log(1.0 / 1e-3))
    clamped = clamp_to_unit(torch.tensor([0.0, 1.0, 0.3]))
    torch.testing.assert_close(clamped, torch.tensor([0.000999, 0.999001, 0.3]), atol=1e-6, rtol=0)


def test_sampling_at_pixel_centres_reads_pixels_exactly():
    feature = torch.arange(12, dtype=torch.float64).view(1, 1, 3, 4)
    points = torch.tensor(
        [[[0.0, 0.0], [3.0, 2.0], [1.0, 2.0], [1.5, 0.0], [-5.0, 9.0]]], dtype=torch.float64
    )
    sampled = sample_at_pixels(feature, points)[0, :, 0]
    assert sampled.tolist() == [0.0, 11.0, 9.0, 1.5, 8.0]  # the last one clamps to the border
