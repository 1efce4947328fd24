"""Frame sources for the window driver: encode each frame once, keep only what is needed."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from taptr.model.taptr import TAPTR, FrameFeatures

FrameLoader = Callable[[int, int], Tensor]
"""Returns frames first..last (inclusive), (B, W_t, 3, H, W) ImageNet-normalised."""


class EncodedFrames:
    """Encodes the frames of a video on demand, window by window.

    A frame is encoded the first time a window asks for it and dropped as soon as a window
    starting after it is requested, so at most one window of memory is held (windows are
    requested in increasing order). Encoding is per frame, so the result equals encoding
    the whole video at once.

    Shape:
        video (B, T, 3, H, W) ImageNet-normalised, or a loader of such frames;
        ``self(first, last)`` → memory (B, last − first + 1, S, C).
    """

    def __init__(self, model: TAPTR, video: Tensor | FrameLoader, chunk_size: int = 1) -> None:
        """Creates the source.

        Args:
            model: the network whose `TAPTR.encode` is used.
            video: (B, T, 3, H, W) ImageNet-normalised frames, or a loader of them.
            chunk_size: frames per encoder call; one keeps the encoder's activations (its
                FFN and sampling intermediates are several times a frame's memory) small.
        """
        self.model = model
        self.load: FrameLoader = (
            video if callable(video) else (lambda first, last: video[:, first : last + 1])
        )
        self.chunk_size = chunk_size
        self.cache: dict[int, Tensor] = {}
        self.spatial_shapes: list[tuple[int, int]] = []

    def __call__(self, first: int, last: int) -> FrameFeatures:
        """Memory of frames first..last (inclusive)."""
        for frame in [f for f in self.cache if f < first]:
            del self.cache[frame]
        missing = [f for f in range(first, last + 1) if f not in self.cache]
        for start in range(0, len(missing), self.chunk_size):
            chunk = missing[start : start + self.chunk_size]
            encoded = self.model.encode(self.load(chunk[0], chunk[-1]))
            self.spatial_shapes = encoded.spatial_shapes
            for offset, frame in enumerate(range(chunk[0], chunk[-1] + 1)):
                self.cache[frame] = encoded.memory[:, offset]
        memory = torch.stack([self.cache[f] for f in range(first, last + 1)], dim=1)
        return FrameFeatures(memory, self.spatial_shapes)


class PrecomputedFrames:
    """A frame source over features encoded beforehand (all frames at once)."""

    def __init__(self, features: FrameFeatures) -> None:
        self.features = features

    def __call__(self, first: int, last: int) -> FrameFeatures:
        """Memory of frames first..last (inclusive)."""
        return FrameFeatures(
            self.features.memory[:, first : last + 1], self.features.spatial_shapes
        )
