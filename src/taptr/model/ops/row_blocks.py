"""Cache-blocked MLP inference: the same arithmetic per row, a block of rows at a time.

An MLP on R rows normally writes one (R, hidden) activation per layer, which for the
encoder's 256 → 2048 → 256 FFN goes through memory rather than the cache. Taking the rows
in blocks keeps each block's hidden activation in the cache; every row still sees the same
products and sums (`taptr.model.layers.MLP` is the reference formulation).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from taptr.model.ops.dense import apply_linear, onednn_applies

ROW_BLOCK = 2048
"""Rows per block in the ``fast`` execution: an FFN's 2,048-wide hidden rows of a block stay
in the caches between its two products, where a whole frame's would not (the block sizes
compared: docs/BENCHMARKS_LOG.md)."""

ENCODER_BLOCK = 4096
"""Tokens per block of an encoder layer in the ``fast`` execution: everything after the
value table (sampling locations, corner rows and weights, output projection, norms, FFN)
for 4,096 tokens is at most about 8 MB per intermediate, where a 512 × 512 frame's 21,760
tokens make them tens of megabytes; smaller blocks pay more small per-block operations (the
sizes compared: docs/BENCHMARKS_LOG.md)."""


def tracks_grad(module: nn.Module, x: Tensor) -> bool:
    """Whether autograd would record a forward of ``module`` on ``x``."""
    if not torch.is_grad_enabled():
        return False
    return x.requires_grad or any(p.requires_grad for p in module.parameters())


def autocasting(x: Tensor) -> bool:
    """Whether autocast is on for ``x``'s device.

    Autocast does not apply to ``out=`` products: they would meet its lower-precision
    activations with float32 weights, so the paths that write into reused buffers step
    aside for plain calls then.
    """
    return torch.is_autocast_enabled(x.device.type)


def use_row_blocks(module: nn.Module, x: Tensor, row_block: int | None) -> bool:
    """Whether to run ``module`` on ``x`` (..., C) in row blocks.

    Only on the CPU (blocks keep intermediates in its caches; on an H200 the blocked
    ``fast`` execution of TAPTRv2 ran at 25.5 frames/s and unblocked at 31.4, 800 points,
    docs/BENCHMARKS.md), with a block size, more rows than one block, nothing for autograd
    to record and no autocast (the ``out=`` products below support neither).
    """
    rows = x.numel() // x.shape[-1]
    return (
        row_block is not None
        and x.device.type == "cpu"
        and rows > row_block
        and not tracks_grad(module, x)
        and not autocasting(x)
    )


def blocked_mlp(layers: nn.ModuleList, x: Tensor, row_block: int, onednn: bool = False) -> Tensor:
    """Linear layers with ReLU between them on (R, in_dim) rows, ``row_block`` at a time.

    Args:
        layers: the `torch.nn.Linear` layers of the MLP.
        x: (R, in_dim) rows.
        row_block: rows per block.
        onednn: run the products as oneDNN inner products (`taptr.model.ops.dense`), the
            ReLUs fused into them, where that applies; elsewhere (GPUs, float64) and
            without it, BLAS products written into reused buffers.

    Returns:
        (R, out_dim).
    """
    linears = [layer for layer in layers if isinstance(layer, nn.Linear)]
    out = x.new_empty(x.shape[0], linears[-1].out_features)
    if onednn and onednn_applies(x, linears[0].weight):
        last = len(linears) - 1
        for start in range(0, x.shape[0], row_block):
            h = x[start : start + row_block]
            for i, layer in enumerate(linears):
                # the last product too: the copy into ``out`` converts it
                h = apply_linear(layer, h, onednn=True, relu=i < last, keep_type=True)
            out[start : start + h.shape[0]] = h
        return out
    # one hidden buffer per inner layer, reused by every block
    hidden = [x.new_empty(row_block, layer.out_features) for layer in linears[:-1]]
    for start in range(0, x.shape[0], row_block):
        h = x[start : start + row_block]
        count = h.shape[0]
        for i, layer in enumerate(linears):
            target = out[start : start + count] if i == len(hidden) else hidden[i][:count]
            h = torch.addmm(layer.bias, h, layer.weight.t(), out=target)
            if i < len(hidden):
                h.relu_()
    return out
