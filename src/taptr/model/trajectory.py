"""The driver's state: per-frame trajectories, the points, and the final output.

The window driver (`taptr.model.sliding_window`) writes results window by window and copies a
window's last frame to all later frames. Keeping those later frames as one shared tensor
makes the copy free, keeps memory bounded by the frames still in use, and lets finished
frames be released. `TrackerState` bundles the trajectories of every point with what the
next window needs; nothing here depends on the network that fills them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import torch
from torch import Tensor

from taptr.model.frame_tables import FrameTables


class Trajectory:
    """Per-frame values of one quantity, from frame ``first`` on, plus the shared future.

    Frames ``first .. first + len(frames) - 1`` are held as separate (B, N, D) tensors;
    every later frame holds ``future``. Writes build new tensors, so autograd sees every
    window's contribution.
    """

    def __init__(self, future: Tensor) -> None:
        self.first = 0
        self.frames: list[Tensor] = []
        self.future = future

    @property
    def end(self) -> int:
        """One past the last held frame."""
        return self.first + len(self.frames)

    def _extend(self, last: int) -> None:
        self.frames.extend([self.future] * (last + 1 - self.end))

    def read(self, first: int, last: int) -> Tensor:
        """Values of frames first..last, (B, W_t, N, D)."""
        if first < self.first:
            raise IndexError(f"frame {first} was already released (first held: {self.first})")
        self._extend(last)
        return torch.stack(self.frames[first - self.first : last + 1 - self.first], dim=1)

    def write(self, first: int, values: Tensor, mask: Tensor) -> None:
        """Overwrites frames first.. where ``mask`` holds.

        Args:
            first: first frame written.
            values: (B, W_t, N, D) new values.
            mask: (B, W_t, N) bool, where to write.
        """
        self._extend(first + values.shape[1] - 1)
        for offset in range(values.shape[1]):
            index = first + offset - self.first
            self.frames[index] = torch.where(
                mask[:, offset, :, None], values[:, offset], self.frames[index]
            )

    def fill(self, select: Tensor, value: Tensor) -> None:
        """Sets every held and future frame of the selected points, (B, N) and (B, N, D)."""
        self.frames = [torch.where(select[..., None], value, f) for f in self.frames]
        self.future = torch.where(select[..., None], value, self.future)

    def pad_from(self, frame: int) -> None:
        """Every frame after ``frame`` takes its value (the official padding)."""
        self.future = self.frames[frame - self.first]
        del self.frames[frame + 1 - self.first :]

    def add_points(self, values: Tensor) -> None:
        """Appends points holding ``values`` (B, n, D) on every held and future frame."""
        self.frames = [torch.cat((f, values), dim=1) for f in self.frames]
        self.future = torch.cat((self.future, values), dim=1)

    def keep_points(self, keep: Tensor) -> None:
        """Keeps only the points selected by the (N,) bool mask."""
        self.frames = [f[:, keep] for f in self.frames]
        self.future = self.future[:, keep]

    def release(self, before: int) -> list[Tensor]:
        """Drops and returns the held frames before ``before``."""
        count = max(0, min(before - self.first, len(self.frames)))
        released, self.frames = self.frames[:count], self.frames[count:]
        self.first += count
        return released


class QuerySet(NamedTuple):
    """The points to track, in model units.

    Attributes:
        start_frames: (B, N) int64 frame where each point is given.
        positions: (B, N, 2) its (x, y) there, normalised by (W − 1, H − 1).
        start_visible: (B, N) bool visibility label at the start frame (only sets the
            visibility logits of frames the model never writes).
    """

    start_frames: Tensor
    positions: Tensor
    start_visible: Tensor


@dataclass
class TrackerState:
    """Everything the next window needs; no other state exists anywhere.

    Attributes:
        queries: the points, in model units.
        num_frames: total video length when known (decides the long-video content rule).
        initial_content: (B, N, C) each point's initial content (zeros until its start
            frame is reached).
        initialised: (B, N) bool, whether ``initial_content`` is set.
        content: the content trajectory.
        positions: per decoder layer, the position-logit trajectory (B, N, 4).
        visibility: per decoder layer, the visibility-logit trajectory (B, N, 3), float32.
        updated_positions: per decoder layer, the APU-updated position logits (B, N, 4);
            empty without the position update.
        next_window: index of the next window to decode.
        tables: the decoder's key and value tables of the frames the next window shares
            with the last one (`taptr.model.frame_tables`).
        start_frames: the points' distinct start frames, in order, on the host, read once
            when points are added or removed: whether a window updates any point, starts
            any and tracks all is decided without asking the device.
        initialised_starts: start frames whose points have taken their content.
    """

    queries: QuerySet
    num_frames: int | None
    initial_content: Tensor
    initialised: Tensor
    content: Trajectory
    positions: list[Trajectory]
    visibility: list[Trajectory]
    updated_positions: list[Trajectory] = field(default_factory=list)
    next_window: int = 0
    tables: FrameTables = field(default_factory=FrameTables)
    start_frames: tuple[int, ...] = ()
    initialised_starts: frozenset[int] = frozenset()


def distinct_starts(queries: QuerySet) -> tuple[int, ...]:
    """The distinct start frames of the queries, in order (read once, when points change)."""
    return tuple(torch.unique(queries.start_frames).tolist())


def joined_starts(starts: tuple[int, ...], more: tuple[int, ...]) -> tuple[int, ...]:
    """The distinct start frames of two point sets joined, in order (no device read)."""
    return tuple(sorted({*starts, *more}))


class TrackOutput(NamedTuple):
    """Full-video trajectories after all windows.

    Attributes:
        positions: (B, T, N, 2) last layer's positions, normalised (x, y).
        visibility_logits: (B, T, N, 3) last layer's logits (channel 1 = visible).
        layer_positions: (D_l, B, T, N, 4) position logits of every layer.
        layer_visibility_logits: (D_l, B, T, N, 3).
        layer_updated_positions: (D_l, B, T, N, 4) APU-updated logits, or None.
    """

    positions: Tensor
    visibility_logits: Tensor
    layer_positions: Tensor
    layer_visibility_logits: Tensor
    layer_updated_positions: Tensor | None


def first_points(output: TrackOutput, count: int) -> TrackOutput:
    """``output`` of its first ``count`` points (views of the same tensors)."""
    return TrackOutput(*(None if part is None else part[..., :count, :] for part in output))


def keep_points(state: TrackerState, keep: Tensor) -> None:
    """Drops the points not selected by the (N,) bool mask from a running state."""
    state.queries = QuerySet(*(q[:, keep] for q in state.queries))
    state.start_frames = distinct_starts(state.queries)
    state.initial_content = state.initial_content[:, keep]
    state.initialised = state.initialised[:, keep]
    for trajectory in [
        state.content,
        *state.positions,
        *state.visibility,
        *state.updated_positions,
    ]:
        trajectory.keep_points(keep)


def finish(state: TrackerState, num_frames: int) -> TrackOutput:
    """Stacks the trajectories of frames 0..T−1 (requires that none was released)."""

    def stack(trajectories: list[Trajectory]) -> Tensor:
        return torch.stack([t.read(0, num_frames - 1) for t in trajectories])  # (D_l, B, T, N, D)

    positions = stack(state.positions)
    visibility = stack(state.visibility)
    updated = stack(state.updated_positions) if state.updated_positions else None
    return TrackOutput(
        positions[-1, ..., :2].sigmoid(), visibility[-1], positions, visibility, updated
    )
