"""Small building blocks shared by the encoder, the decoder and the heads."""

from __future__ import annotations

import itertools

import torch
import torch.nn.functional as F
from torch import Tensor, nn

ROW_BLOCK = 512
"""Rows per block of `MLP.row_block` by default: a (512, 2048) float32 hidden block is 4 MB,
about a core's share of cache (256-1024 measured alike; unblocked, the encoder FFN is 1.5x
slower on one thread)."""


class MLP(nn.Module):
    """Linear layers with ReLU between them (none after the last).

    Attributes:
        row_block: when set, inference (no autograd) runs the layers on blocks of this many
            rows at a time, so that a block's hidden activations stay in the CPU cache instead
            of one (rows, hidden) tensor going through memory; each row's arithmetic is the
            same. ``None`` runs all rows at once (the faithful path, see `taptr.model.paths`).

    Shape:
        (..., in_dim) → (..., out_dim).
    """

    def __init__(self, in_dim: int, hidden_dim: int, out_dim: int, num_layers: int) -> None:
        super().__init__()
        dims = [in_dim] + [hidden_dim] * (num_layers - 1) + [out_dim]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in itertools.pairwise(dims))
        self.row_block: int | None = ROW_BLOCK

    def forward(self, x: Tensor) -> Tensor:
        """Applies the layers."""
        rows = x.numel() // x.shape[-1]
        if self.row_block is not None and rows > self.row_block and not _tracks_grad(self, x):
            return self._blocked(x.reshape(rows, x.shape[-1])).view(*x.shape[:-1], -1)
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i < len(self.layers) - 1:
                x = F.relu(x)
        return x

    def _blocked(self, x: Tensor) -> Tensor:
        """`forward` on (R, in_dim) rows, ``row_block`` rows at a time; (R, out_dim)."""
        block = self.row_block
        assert block is not None
        out = x.new_empty(x.shape[0], self.layers[-1].out_features)
        hidden = [x.new_empty(block, layer.out_features) for layer in self.layers[:-1]]
        for start in range(0, x.shape[0], block):
            h = x[start : start + block]
            count = h.shape[0]
            for i, layer in enumerate(self.layers):
                target = out[start : start + count] if i == len(hidden) else hidden[i][:count]
                h = torch.addmm(layer.bias, h, layer.weight.t(), out=target)
                if i < len(hidden):
                    h.relu_()
        return out


def _tracks_grad(module: nn.Module, x: Tensor) -> bool:
    """Whether autograd would record a forward of ``module`` on ``x``."""
    if not torch.is_grad_enabled():
        return False
    return x.requires_grad or any(p.requires_grad for p in module.parameters())
