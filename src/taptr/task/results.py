"""The records a tracker hands back, whichever engine ran it.

`Predictor` and `OnlineTracker` fill them with torch tensors, the exported loop
(`taptr.onnx`) with numpy arrays; the fields, their shapes and their meaning are the same.

Shapes: T frames, F frames of one update, N points.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple


class TrackArrays(NamedTuple):
    """Tracks of a whole video in model units (numpy).

    Attributes:
        positions: (T, N, 2) float32 (x, y) normalised by (W − 1, H − 1).
        visibility_logits: (T, N, 3) float32 (channel 1 = visible).
    """

    positions: Any
    visibility_logits: Any


@dataclass
class StreamUpdate:
    """Tracks of the frames of a stream that became final.

    Attributes:
        first_frame: index of the first returned frame.
        tracks: (F, N, 2) float32 (x, y) pixels of the input frames.
        visibility: (F, N) bool.
        visibility_logits: (F, N) float32; −inf before a point's query frame.
        point_ids: identifier of each of the N points.
    """

    first_frame: int
    tracks: Any
    visibility: Any
    visibility_logits: Any
    point_ids: list[int]


class FrameCountError(ValueError):
    """A stream brought more or fewer frames than its tracker's ``start`` was told.

    Attributes:
        seen: frames received (with the chunk that went past the count, when too many).
        declared: frames ``start`` was told.
    """

    def __init__(self, message: str, *, seen: int, declared: int) -> None:
        super().__init__(message)
        self.seen = seen
        self.declared = declared

    @property
    def short(self) -> bool:
        """Whether the stream ended before the declared count (a truncated file)."""
        return self.seen < self.declared
