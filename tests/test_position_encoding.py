"""Sine encodings against hand-computed values."""

from __future__ import annotations

import math

import torch

from taptr.model.position_encoding import feature_map_encoding, point_embedding, sine_embedding


def test_sine_embedding_channels():
    value = 0.3
    emb = sine_embedding(
        torch.tensor([[value]], dtype=torch.float64), channels=8, temperature=10.0
    )[0]
    for k in range(8):
        angle = value * 2 * math.pi / 10 ** (2 * (k // 2) / 8)
        expected = math.sin(angle) if k % 2 == 0 else math.cos(angle)
        assert abs(emb[k].item() - expected) < 1e-6  # the frequency table is float32


def test_point_embedding_puts_y_first():
    xy = torch.tensor([[0.1, 0.7, 0.5, 0.5]])
    emb = point_embedding(xy, channels=4, temperature=10.0)
    torch.testing.assert_close(emb[0, :4], sine_embedding(torch.tensor([[0.7]]), 4, 10.0)[0])
    torch.testing.assert_close(emb[0, 4:8], sine_embedding(torch.tensor([[0.1]]), 4, 10.0)[0])


def test_feature_map_encoding_is_one_based_and_normalised():
    encoding = feature_map_encoding(2, 3, channels=4, temperature=10.0, device=torch.device("cpu"))
    assert encoding.shape == (6, 8)
    row, col = 1, 2  # token 5
    y = (row + 1) / (2 + 1e-6) * 2 * math.pi
    x = (col + 1) / (3 + 1e-6) * 2 * math.pi
    assert abs(encoding[5, 0].item() - math.sin(y)) < 1e-6
    assert abs(encoding[5, 1].item() - math.cos(y)) < 1e-6
    assert abs(encoding[5, 4].item() - math.sin(x)) < 1e-6
    assert abs(encoding[5, 6].item() - math.sin(x / 10 ** (2 / 4))) < 1e-6
