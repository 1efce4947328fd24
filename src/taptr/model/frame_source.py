"""How encoded frames reach a driver: the features of a span of frames, asked for by index.

Both drivers (the windows of `taptr.model.sliding_window`, the frames of
`taptr.model.v3.per_frame`) read their frames through a `FrameSource`, so that what encodes
them (the PyTorch encoder on demand, `taptr.runtime.frames`; the exported encoder graph,
`taptr.export.graph_runner.GraphFrames`; features encoded beforehand) is none of their
concern.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

from torch import Tensor


class FrameFeatures(NamedTuple):
    """Encoder memory of some frames.

    Attributes:
        memory: (B, T, S, C) tokens of all levels, flattened row-major per level.
        spatial_shapes: (H_l, W_l) of the L levels.
    """

    memory: Tensor
    spatial_shapes: list[tuple[int, int]]


FrameSource = Callable[[int, int], FrameFeatures]
"""Returns the features of frames first..last (inclusive), memory (B, W_t, S, C)."""

Span = tuple[int, int]
"""First and last frame (inclusive) of a unit of decoding: a window, or one frame."""
