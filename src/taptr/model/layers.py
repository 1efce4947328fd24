"""Small building blocks shared by the encoder, the decoder and the heads."""

from __future__ import annotations

import itertools

from torch import Tensor, nn

from taptr.model.execution import Execution
from taptr.model.ops.dense import apply_linear
from taptr.model.ops.row_blocks import blocked_mlp, use_row_blocks


class MLP(nn.Module):
    """Linear layers with ReLU between them (none after the last).

    Shape:
        (..., in_dim) → (..., out_dim).
    """

    def __init__(self, in_dim: int, hidden_dim: int, out_dim: int, num_layers: int) -> None:
        super().__init__()
        dims = [in_dim] + [hidden_dim] * (num_layers - 1) + [out_dim]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in itertools.pairwise(dims))

    def forward(self, x: Tensor, execution: Execution | None = None) -> Tensor:
        """Applies the layers.

        Args:
            x: (..., in_dim) rows.
            execution: how inference runs them (`taptr.model.execution.Execution`): with a
                ``row_block``, the rows in blocks of this many (`taptr.model.ops.row_blocks`,
                the same arithmetic per row); with ``onednn_linear``, the products through
                oneDNN (`taptr.model.ops.dense`). None runs all rows at once with
                ``F.linear``, the reference.
        """
        onednn = execution is not None and execution.onednn_linear
        row_block = None if execution is None else execution.row_block
        if use_row_blocks(self, x, row_block):
            assert row_block is not None
            rows = x.reshape(-1, x.shape[-1])  # (R, in_dim)
            return blocked_mlp(self.layers, rows, row_block, onednn).view(*x.shape[:-1], -1)
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            x = apply_linear(layer, x, onednn=onednn, relu=i < last, keep_type=i < last)
        return x
