"""The attention-based position update against a hand computation."""

from __future__ import annotations

import torch

from taptr.model.position_update import PositionUpdate, normalize_offsets


def test_normalization_divides_x_by_height_and_y_by_width():
    offsets = torch.tensor([[[3.0, 4.0]], [[3.0, 4.0]]])  # (L=2, P=1, 2)
    moved = normalize_offsets(offsets, [(2, 8), (4, 16)])
    torch.testing.assert_close(moved, torch.tensor([[[1.5, 0.5]], [[0.75, 0.25]]]))


def test_disentangler_update_is_the_softmax_weighted_offset():
    update = PositionUpdate(num_samples=2 * 1 * 2, hidden_dim=8, disentangler=True)
    with torch.no_grad():
        # make the MLP the identity on non-negative inputs: Linear(4→8) = [I; 0], Linear(8→8) = I,
        # Linear(8→4) = [I 0]
        layers = update.disentangler.layers
        layers[0].weight.zero_()
        layers[0].weight[:4, :4] = torch.eye(4)
        layers[1].weight.copy_(torch.eye(8))
        layers[2].weight.zero_()
        layers[2].weight[:, :4] = torch.eye(4)
        for layer in layers:
            layer.bias.zero_()
    logits = torch.tensor([1.0, 2.0, 0.0, 3.0]).view(1, 1, 2, 1, 2)  # (B, Q, M, L, P)
    offsets = torch.tensor([[2.0, 0.0], [0.0, 4.0], [-2.0, 2.0], [4.0, 4.0]]).view(1, 1, 2, 1, 2, 2)
    delta = update(logits, offsets, [(4, 8)])  # x / 4, y / 8
    weights = torch.tensor([1.0, 2.0, 0.0, 3.0]).softmax(0)  # joint over heads and points
    moves = torch.tensor([[0.5, 0.0], [0.0, 0.5], [-0.5, 0.25], [1.0, 0.5]])
    torch.testing.assert_close(delta.view(2), weights @ moves)


def test_without_disentangler_content_weights_are_averaged_over_heads():
    update = PositionUpdate(num_samples=4, hidden_dim=8, disentangler=False)
    assert list(update.parameters()) == []
    logits = torch.tensor([0.0, 0.0, 0.0, 10.0]).view(1, 1, 2, 1, 2)
    offsets = torch.tensor([[2.0, 0.0], [0.0, 2.0], [4.0, 4.0], [8.0, 0.0]]).view(1, 1, 2, 1, 2, 2)
    delta = update(logits, offsets, [(2, 2)])
    head0 = 0.5 * torch.tensor([1.0, 0.0]) + 0.5 * torch.tensor([0.0, 1.0])
    w = torch.tensor([0.0, 10.0]).softmax(0)
    head1 = w[0] * torch.tensor([2.0, 2.0]) + w[1] * torch.tensor([4.0, 0.0])
    torch.testing.assert_close(delta.view(2), (head0 + head1) / 2)
