"""The window engine: TAPTR v1 and TAPTRv2, decoded window by window.

A whole video is `taptr.model.sliding_window.run_windows`. A stream decodes a window once
a frame after it has arrived (so that a point added on the newest frame still joins it),
and a frame is final once no later window contains it: about one window behind.
"""

from __future__ import annotations

import torch
from torch import Tensor

from taptr.model.frame_source import FrameSource, Span
from taptr.model.sliding_window import (
    WindowNetwork,
    add_points,
    decode_window,
    keep_points,
    run_windows,
    start_state,
)
from taptr.model.taptr import TAPTR
from taptr.model.trajectory import QuerySet, TrackerState, TrackOutput
from taptr.types import OnStep
from taptr.windows import window_ranges


class WindowEngine:
    """Runs a windowed model (a `TAPTR`, or another `WindowNetwork` such as exported graphs).

    Args:
        model: the PyTorch network or another `WindowNetwork`.
        dtype: floating dtype of the positions and content.
    """

    unit = "window"

    def __init__(self, model: TAPTR | WindowNetwork, dtype: torch.dtype) -> None:
        self.model = model
        self.dtype = dtype

    def steps(self, num_frames: int) -> int:
        """How many windows a video of ``num_frames`` has (`run`'s ``on_step`` calls)."""
        return len(window_ranges(num_frames, self.model.window_size, self.model.window_stride))

    def run(
        self, queries: QuerySet, num_frames: int, frames: FrameSource, on_step: OnStep = None
    ) -> TrackOutput:
        """Tracks the queries through a whole video, window by window (`Engine.run`)."""
        return run_windows(self.model, queries, num_frames, frames, self.dtype, on_step)

    def start(self, queries: QuerySet, num_frames: int | None) -> TrackerState:
        """The driver state of a new stream."""
        return start_state(self.model, queries, num_frames, self.dtype)

    def queries(self, state: TrackerState) -> QuerySet:
        """The points the state tracks."""
        return state.queries

    def add_points(self, state: TrackerState, queries: QuerySet) -> None:
        """Appends points (`taptr.model.sliding_window.add_points`)."""
        add_points(self.model, state, queries)

    def keep_points(self, state: TrackerState, keep: Tensor) -> None:
        """Keeps the points selected by the (N,) bool mask."""
        keep_points(state, keep)

    def next_span(self, state: TrackerState, num_frames: int | None) -> Span | None:
        """The next window, or None when a declared stream has no more."""
        index, size, stride = state.next_window, self.model.window_size, self.model.window_stride
        if num_frames is None:
            return index * stride, index * stride + size - 1
        ranges = window_ranges(num_frames, size, stride)
        return ranges[index] if index < len(ranges) else None

    def remaining(self, state: TrackerState, num_seen: int) -> list[Span]:
        """The windows still to decode when the stream ends after ``num_seen`` frames."""
        ranges = window_ranges(num_seen, self.model.window_size, self.model.window_stride)
        return ranges[state.next_window :]

    def decode(self, state: TrackerState, span: Span, frames: FrameSource) -> None:
        """Decodes one window."""
        decode_window(self.model, state, span[0], span[1], frames)

    def final_bound(self, state: TrackerState, num_seen: int, num_frames: int | None) -> int:
        """Frames before this index can no longer change."""
        if state.next_window == 0:
            return 0
        upcoming = self.next_span(state, num_frames)
        if num_frames is not None:
            return num_frames if upcoming is None else upcoming[0]
        # an undeclared stream may still end with a window shifted back to [T - size, T - 1]
        assert upcoming is not None
        return max(0, min(upcoming[0], num_seen - self.model.window_size))

    def read(self, state: TrackerState, first: int, bound: int) -> tuple[Tensor, Tensor]:
        """Last-layer positions (F, N, 2) normalised and logits (F, N) of frames first..bound−1."""
        positions = state.positions[-1].read(first, bound - 1)[0, ..., :2].sigmoid()
        return positions, state.visibility[-1].read(first, bound - 1)[0, ..., 1]

    def release(self, state: TrackerState, before: int) -> None:
        """Forgets the trajectories of frames before ``before``."""
        for trajectory in [
            state.content,
            *state.positions,
            *state.visibility,
            *state.updated_positions,
        ]:
            trajectory.release(before)
