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
    starting after it is requested, so at most one window of memory is held, plus the
    frames read ahead (windows are requested in increasing order). Encoding is per frame,
    so the result equals encoding the whole video at once, up to the rounding a kernel's
    batch size may change.

    Shape:
        video (B, T, 3, H, W) ImageNet-normalised, or a loader of such frames;
        ``self(first, last)`` → memory (B, last − first + 1, S, C).
    """

    def __init__(
        self,
        model: TAPTR,
        video: Tensor | FrameLoader,
        chunk_size: int = 1,
        num_frames: int | None = None,
    ) -> None:
        """Creates the source.

        Args:
            model: the network whose `TAPTR.encode` is used.
            video: (B, T, 3, H, W) ImageNet-normalised frames, or a loader of them.
            chunk_size: frames per encoder call. One keeps the encoder's activations (its
                FFN and sampling intermediates are several times a frame's memory) small;
                more pays where a call's fixed cost dominates (small frames, GPUs:
                `taptr.runtime.encode_choice`).
            num_frames: frames that can be loaded (the video's length; a stream updates
                it as frames arrive). Given, a call that must encode reads ahead to fill
                its chunk with frames the next windows will ask for; without it only the
                requested frames are encoded.
        """
        self.model = model
        self.load: FrameLoader = (
            video if callable(video) else (lambda first, last: video[:, first : last + 1])
        )
        self.chunk_size = chunk_size
        self.num_frames = (
            num_frames if num_frames is not None else (None if callable(video) else video.shape[1])
        )
        self.cache: dict[int, Tensor] = {}
        self.spatial_shapes: list[tuple[int, int]] = []

    def __call__(self, first: int, last: int) -> FrameFeatures:
        """Memory of frames first..last (inclusive)."""
        for frame in [f for f in self.cache if f < first]:
            del self.cache[frame]
        frame = first
        while frame <= last:
            if frame in self.cache:
                frame += 1
                continue
            end = self._chunk_end(frame, last)
            self._encode(frame, end)
            frame = end + 1
        memory = torch.stack([self.cache[f] for f in range(first, last + 1)], dim=1)
        return FrameFeatures(memory, self.spatial_shapes)

    def _chunk_end(self, start: int, last: int) -> int:
        """The last frame of the chunk that encodes ``start``.

        A full chunk where the video has the frames; never past a frame already encoded.
        """
        limit = last if self.num_frames is None else self.num_frames - 1
        end = start
        while end < min(start + self.chunk_size - 1, limit) and end + 1 not in self.cache:
            end += 1
        return end

    def _encode(self, first: int, last: int) -> None:
        encoded = self.model.encode(self.load(first, last))  # memory (B, F, S, C)
        self.spatial_shapes = encoded.spatial_shapes
        for offset, frame in enumerate(range(first, last + 1)):
            self.cache[frame] = encoded.memory[:, offset]


class PrecomputedFrames:
    """A frame source over features encoded beforehand (all frames at once)."""

    def __init__(self, features: FrameFeatures) -> None:
        self.features = features

    def __call__(self, first: int, last: int) -> FrameFeatures:
        """Memory of frames first..last (inclusive)."""
        return FrameFeatures(
            self.features.memory[:, first : last + 1], self.features.spatial_shapes
        )
