"""A video's frames handed to the model as it asks for them, forward or backward in time.

The runner encodes frames window by window (`taptr.runtime.frames.EncodedFrames`), so the
predictor never prepares (resizes, normalises) the whole video at once: it hands over a
`PreparedFrames`, which slices the frames asked for and prepares only those. Read backwards
(the reversed pass of `taptr.api.backward`), frame t is frame T − 1 − t, without a reversed
copy of the video.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from torch import Tensor


@dataclass(frozen=True)
class PreparedFrames:
    """Frames first..last of a video, prepared for the model.

    Attributes:
        frames: (T, 3, H, W) the video, uint8 or floats in [0, 1].
        prepare: (F, 3, H, W) frames → (1, F, 3, H_m, W_m) model input
            (`taptr.api.predictor.Predictor.prepare`).
        reverse: read the video backwards.
    """

    frames: Tensor
    prepare: Callable[[Tensor], Tensor]
    reverse: bool = False

    def __call__(self, first: int, last: int) -> Tensor:
        """(1, last − first + 1, 3, H_m, W_m): frames first..last of the pass."""
        if self.reverse:
            count = self.frames.shape[0]
            return self.prepare(self.frames[count - 1 - last : count - first].flip(0))
        return self.prepare(self.frames[first : last + 1])
