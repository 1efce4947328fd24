"""The frames a stream holds: the predictor's frame cache, fed by frames as they arrive.

The predictor reads its video through `EncodedFrames`, which encodes each frame once, when
the first window needs it, and keeps at most one window. A stream cannot be read on demand,
so arriving frames wait here, prepared for the model, until a window asks for them; the
same `EncodedFrames` then encodes them exactly as the offline predictor does.
"""

from __future__ import annotations

import torch
from torch import Tensor

from taptr.model.taptr import TAPTR, FrameFeatures
from taptr.runtime.frames import EncodedFrames


class StreamFrames:
    """Frames of a stream still needed by the windows to decode.

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
