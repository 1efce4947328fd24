"""The per-point history TAPTRv3's long-temporal attention reads: content and visibility.

For a point that started on frame s, decoding frame f reads the frames it holds, oldest
first (the official streaming placeholder, in our words):

- frames before s: its initial content (written over every held frame when it starts),
  weight 0;
- frame s: the last layer's head features of frame s if that frame was decoded, else
  its initial content; weight 1;
- frames s < j < f: the last layer's head features of frame j; weight σ(visibility logit
  of frame j), detached;
- frame f itself: its initial content; weight σ of its still-initial "occluded" logit,
  ≈ 0.001 (visibility is never carried forward).

Without a limit every frame since the first is held; with ``limit`` = P only the last P
(the current one included), oldest dropped first, which bounds memory on long videos
(the official ``streaming_limited_size_of_placeholder``). Frames are kept in one buffer
that grows by doubling and, with a limit, slides back to its start when full, so each
frame costs amortised O(N · C) to hold.
"""

from __future__ import annotations

import torch
from torch import Tensor


class History:
    """Held frames of every point: content (B, N, H, C) and last-layer visibility (B, N, H).

    Attributes:
        first: video frame of the oldest held frame.
        length: H, how many frames are held.
        limit: the most frames held (0: no limit).
    """

    def __init__(self, batch: int, channels: int, limit: int, like: Tensor) -> None:
        """An empty history for ``batch`` videos and no points; tensors like ``like``."""
        self.first = 0
        self.length = 0
        self.limit = limit
        self._start = 0  # buffer slot of the oldest held frame
        self._content = like.new_zeros(batch, 0, 0, channels)
        self._visibility = torch.zeros(batch, 0, 0, device=like.device)

    @property
    def content(self) -> Tensor:
        """(B, N, H, C) held content, oldest first (a view of the buffer)."""
        return self._content[:, :, self._start : self._start + self.length]

    @property
    def visibility_logits(self) -> Tensor:
        """(B, N, H) float32 last-layer visibility logit (channel 1) of each held frame."""
        return self._visibility[:, :, self._start : self._start + self.length]

    def frames(self) -> Tensor:
        """(H,) int64 video frame of each held frame."""
        return torch.arange(self.first, self.first + self.length, device=self._content.device)

    @property
    def slot_content(self) -> Tensor:
        """(B, N, capacity, C) the whole buffer, slots in order (see `slot_frames`)."""
        return self._content

    @property
    def slot_visibility_logits(self) -> Tensor:
        """(B, N, capacity) float32 logits of the whole buffer."""
        return self._visibility

    def slot_frames(self) -> Tensor:
        """(capacity,) int64 frame each buffer slot would hold, counted from the oldest held.

        Slots before the oldest held frame count back from it, slots after the newest
        count on: only those in [``first``, ``first + length``) hold frames.
        """
        origin = self.first - self._start
        capacity = self._content.shape[2]
        return torch.arange(origin, origin + capacity, device=self._content.device)

    def open_frame(self, frame: int, content: Tensor, visibility_logit: Tensor) -> None:
        """Holds ``frame`` (the next one), starting at the points' initial values.

        Args:
            frame: the frame about to be decoded (``first + length``, or the first ever).
            content: (B, N, C) each point's initial content.
            visibility_logit: (B, N) its initial last-layer logit on this frame.
        """
        if self.length == 0:
            self.first = frame
        elif frame != self.first + self.length:
            raise ValueError(f"frames must be held in order: expected {self.first + self.length}")
        if self.limit and self.length == self.limit:
            self._start += 1
            self.first += 1
            self.length -= 1
        self._detach_from_graphs()
        self._make_room()
        slot = self._start + self.length
        self._content[:, :, slot] = content
        self._visibility[:, :, slot] = visibility_logit.float()
        self.length += 1

    def close_frame(self, features: Tensor, visibility_logit: Tensor, update: Tensor) -> None:
        """Writes the decoded newest frame: features for every point, logits where updated.

        Args:
            features: (B, N, C) the last layer's head features of every point (the official
                write is not masked: untracked points are written over when they start).
            visibility_logit: (B, N) the last layer's logit (channel 1).
            update: (B, N) bool, points updated on this frame.
        """
        slot = self._start + self.length - 1
        self._detach_from_graphs()
        self._content[:, :, slot] = features
        held = self._visibility[:, :, slot]
        self._visibility[:, :, slot] = torch.where(update, visibility_logit.detach().float(), held)

    def restart(self, select: Tensor, content: Tensor) -> None:
        """Sets every held frame of the selected points to their initial content.

        Args:
            select: (B, N) bool, points starting now.
            content: (B, N, C) their initial content.
        """
        fresh = torch.where(select[..., None, None], content[:, :, None], self.content)
        self._detach_from_graphs()
        self._content[:, :, self._start : self._start + self.length] = fresh

    def add_points(self, count: int) -> None:
        """Appends ``count`` points holding zeros (they are restarted when they start)."""
        batch, _, slots, channels = self._content.shape
        fresh = self._content.new_zeros(batch, count, slots, channels)
        self._content = torch.cat((self._content, fresh), 1)
        self._visibility = torch.cat(
            (self._visibility, self._visibility.new_zeros(batch, count, slots)), 1
        )

    def keep_points(self, keep: Tensor) -> None:
        """Keeps only the points selected by the (N,) bool mask."""
        self._content = self._content[:, keep]
        self._visibility = self._visibility[:, keep]

    def _detach_from_graphs(self) -> None:
        """Under autograd, writes go to a copy: earlier frames' graphs saved the old buffer."""
        if torch.is_grad_enabled():
            self._content = self._content.clone()

    def _make_room(self) -> None:
        """Ensures one free slot after the held frames (slide back or grow by doubling)."""
        capacity = self._content.shape[2]
        if self._start + self.length < capacity:
            return
        if self.limit and self.length < capacity // 2:
            # slide the held frames back to the start of the buffer
            self._content[:, :, : self.length] = self.content.clone()
            self._visibility[:, :, : self.length] = self.visibility_logits.clone()
            self._start = 0
            return
        # doubling with the frames actually held: a limit longer than the video costs
        # nothing; with a limit the buffer stops at twice it, where sliding back pays
        wanted = max(2 * self.length, 8)
        if self.limit:
            wanted = min(wanted, max(2 * self.limit, 8))
        batch, points, _, channels = self._content.shape
        content = self._content.new_zeros(batch, points, wanted, channels)
        visibility = self._visibility.new_zeros(batch, points, wanted)
        content[:, :, : self.length] = self.content
        visibility[:, :, : self.length] = self.visibility_logits
        self._content, self._visibility, self._start = content, visibility, 0


def frame_weights(
    frames: Tensor, start_frames: Tensor, visibility_logits: Tensor, weighted: bool
) -> Tensor:
    """Long-temporal weights of the held frames for each point.

    Args:
        frames: (H,) video frame of each held frame.
        start_frames: (B, N) each point's start frame.
        visibility_logits: (B, N, H) float32 last-layer logits of the held frames.
        weighted: visibility weights (float, the paper) or the frames at or after the
            start (bool, the ablation).

    Returns:
        (B, N, H): float weights (0 before the start, 1 on it, σ(logit) after) or bool.
    """
    held = frames[None, None, :]  # (1, 1, H)
    starts = start_frames[..., None]  # (B, N, 1)
    if not weighted:
        return held >= starts
    weights = visibility_logits.sigmoid()
    weights = torch.where(held == starts, torch.ones_like(weights), weights)
    return torch.where(held < starts, torch.zeros_like(weights), weights)
