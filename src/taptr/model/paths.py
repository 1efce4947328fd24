"""The faithful and the fast execution path of one model; their outputs agree up to rounding.

The faithful path is the straightforward formulation (``grid_sample`` deformable attention,
explicit N × N attention masks); the fast path gathers samples with ``embedding_bag`` and
runs point attention on the tracked points of each frame only, and its MLPs (the encoder's
FFN above all) take their rows in cache-sized blocks at inference. Benchmarks use the faithful
path as their baseline; everything else runs the fast path, the default.
"""

from __future__ import annotations

from torch import nn

from taptr.model.decoder import Decoder
from taptr.model.layers import MLP, ROW_BLOCK
from taptr.model.ops import set_kernel

PATHS = ("faithful", "fast")


def use_path(model: nn.Module, name: str) -> nn.Module:
    """Switches ``model`` to the faithful or the fast path; returns the model."""
    if name not in PATHS:
        raise ValueError(f"unknown path {name!r}; choose from {', '.join(PATHS)}")
    faithful = name == "faithful"
    set_kernel(model, "grid_sample" if faithful else "gather")
    for module in model.modules():
        if isinstance(module, Decoder):
            module.grouped_attention = not faithful
        if isinstance(module, MLP):
            module.row_block = None if faithful else ROW_BLOCK
    return model
