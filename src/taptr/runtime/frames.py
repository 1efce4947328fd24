"""The frame caches a driver reads: each frame encoded once, only what is needed kept.

`EncodedFrames` encodes a video's frames on demand (a frame the first time a window or a
frame step asks for it, several per encoder call where that pays); `StreamFrames` holds a
stream's arriving frames until it asks; `PrecomputedFrames` serves features encoded
beforehand. All three are a `taptr.model.frame_source.FrameSource`.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from taptr.model.frame_source import FrameFeatures
from taptr.model.taptr import TAPTR

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


class StreamFrames:
    """Frames of a stream still needed by the units to decode.

    A stream cannot be read on demand, so arriving frames wait here, prepared for the model,
    until a unit asks for them; an `EncodedFrames` then encodes them exactly as for a
    whole video.

    Shape:
        ``add(first, frames)``: frames (1, F, 3, H_m, W_m) prepared model input;
        ``self(first, last)`` → memory (1, last − first + 1, S, C).
    """

    def __init__(self, model: TAPTR, frames_per_call: int = 1) -> None:
        self.waiting: dict[int, Tensor] = {}  # frame index → (1, 1, 3, H_m, W_m), not encoded
        # no length: `__call__` lets it read ahead through the frames that have arrived
        self.encoded = EncodedFrames(model, self._load, frames_per_call)

    def add(self, first: int, frames: Tensor) -> None:
        """Holds prepared frames (1, F, 3, H_m, W_m), frames first..first + F − 1."""
        for offset in range(frames.shape[1]):
            self.waiting[first + offset] = frames[:, offset : offset + 1]

    def __call__(self, first: int, last: int) -> FrameFeatures:
        """Memory of frames first..last (inclusive); earlier frames are dropped."""
        self.encoded.num_frames = max(last, *self.waiting) + 1 if self.waiting else last + 1
        return self.encoded(first, last)

    def release(self, before: int) -> None:
        """Drops waiting frames before ``before`` (windows skipped for lack of points)."""
        for frame in [f for f in self.waiting if f < before]:
            del self.waiting[frame]

    def __len__(self) -> int:
        """Frames held: waiting ones, and the encoded ones `EncodedFrames` keeps."""
        return len(self.waiting) + len(self.encoded.cache)

    def _load(self, first: int, last: int) -> Tensor:
        """Prepared frames first..last, (1, last − first + 1, 3, H_m, W_m), no longer held."""
        return torch.cat([self.waiting.pop(f) for f in range(first, last + 1)], dim=1)
