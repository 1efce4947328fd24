"""Each point's held frames for the exported TAPTRv3 step, in numpy: a ring buffer.

What is held follows the PyTorch driver (`taptr.model.v3.history`, whose module docstring
gives the reading rule): every frame since the first one decoded, or the last P with a
limit P (the current one included, oldest dropped first). How it is held is the
loop's own business, since ``decode_step`` reads the whole buffer with each slot's frame
(``slot_frames``) and whether it holds one (``slot_held``): here frame f lives in slot
f mod H of a buffer of H slots, which doubles (from `MIN_SLOTS`, up to the limit) when
every slot is held, so a frame costs O(N · C) to hold and a full FIFO buffer overwrites
its oldest slot in place.

Shapes: N points, H slots, C channels.
"""

from __future__ import annotations

import numpy as np

from taptr.config import check_history_frames

MIN_SLOTS = 8
"""Slots of the first buffer."""


class RingHistory:
    """Held content (N, H, C) and last-layer visibility logits (N, H) of every point.

    Attributes:
        content: (N, H, C) float32 the buffer's content.
        visibility: (N, H) float32 the slots' last-layer logits (channel 1).
        slot_frames: (H,) int64 the frame each slot holds (−1 before it held one).
        slot_held: (H,) bool, slots holding one of the held frames.
        first: the oldest held frame.
        length: how many frames are held.
        limit: the most frames held (0: no limit).
    """

    def __init__(self, channels: int, limit: int) -> None:
        """An empty history of no points.

        Raises:
            ValueError: a limit of 1 or below 0.
        """
        check_history_frames(limit)
        self.limit = limit
        self.first = 0
        self.length = 0
        slots = min(MIN_SLOTS, limit) if limit else MIN_SLOTS
        self.content = np.zeros((0, slots, channels), np.float32)
        self.visibility = np.zeros((0, slots), np.float32)
        self.slot_frames = np.full(slots, -1, np.int64)
        self.slot_held = np.zeros(slots, bool)

    def open_frame(self, frame: int, content: np.ndarray, visibility_logit: np.ndarray) -> None:
        """Holds ``frame`` (the next one), starting at the points' initial values.

        Args:
            frame: the frame about to be decoded (the one after the newest held).
            content: (N, C) each point's initial content.
            visibility_logit: (N,) its logit on this frame before decoding.

        Raises:
            ValueError: a frame out of order.
        """
        if self.length == 0:
            self.first = frame
        elif frame != self.first + self.length:
            raise ValueError(f"frames must be held in order: expected {self.first + self.length}")
        if self.limit and self.length == self.limit:  # drop the oldest
            self.slot_held[self.first % len(self.slot_held)] = False
            self.first += 1
            self.length -= 1
        if self.length == len(self.slot_held):
            self._grow()
        slot = frame % len(self.slot_held)
        self.content[:, slot] = content
        self.visibility[:, slot] = visibility_logit
        self.slot_frames[slot] = frame
        self.slot_held[slot] = True
        self.length += 1

    def close_frame(self, features: np.ndarray, visibility_logit: np.ndarray) -> None:
        """Writes the decoded newest frame.

        Args:
            features: (N, C) the last layer's head features of every point.
            visibility_logit: (N,) the frame's last-layer logit (its value before
                decoding where the point was not updated).
        """
        slot = (self.first + self.length - 1) % len(self.slot_held)
        self.content[:, slot] = features
        self.visibility[:, slot] = visibility_logit

    def restart(self, select: np.ndarray, content: np.ndarray) -> None:
        """Sets every held frame of the selected points to their initial content.

        Args:
            select: (N,) bool, points starting now.
            content: (N, C) their initial content (rows of other points are not read).
        """
        rows = np.flatnonzero(select)
        slots = np.flatnonzero(self.slot_held)
        self.content[np.ix_(rows, slots)] = content[rows, None]

    def add_points(self, count: int) -> None:
        """Appends ``count`` points holding zeros (they are restarted when they start)."""
        _, slots, channels = self.content.shape
        self.content = np.concatenate(
            (self.content, np.zeros((count, slots, channels), np.float32))
        )
        self.visibility = np.concatenate((self.visibility, np.zeros((count, slots), np.float32)))

    def keep_points(self, keep: np.ndarray) -> None:
        """Keeps only the points selected by the (N,) bool mask."""
        self.content = np.ascontiguousarray(self.content[keep])
        self.visibility = np.ascontiguousarray(self.visibility[keep])

    def _grow(self) -> None:
        """Doubles the slots (up to the limit); each held frame f moves to slot f mod H."""
        old = len(self.slot_held)
        slots = min(2 * old, self.limit) if self.limit else 2 * old
        points, _, channels = self.content.shape
        content = np.zeros((points, slots, channels), np.float32)
        visibility = np.zeros((points, slots), np.float32)
        frames = np.full(slots, -1, np.int64)
        held = np.zeros(slots, bool)
        for frame in range(self.first, self.first + self.length):
            source, target = frame % old, frame % slots
            content[:, target] = self.content[:, source]
            visibility[:, target] = self.visibility[:, source]
            frames[target], held[target] = frame, True
        self.content, self.visibility = content, visibility
        self.slot_frames, self.slot_held = frames, held
