"""How a stream runs each model family: windows (TAPTR v1, TAPTRv2) or frames (TAPTRv3).

`taptr.api.online.OnlineTracker` asks an engine for the next unit of frames it can
decode (a window, or one frame), decodes it, and reads the frames that became final. The
engines hold no state of their own: everything lives in the stream's driver state.

- `WindowEngine`: a window is decoded once a frame after it has arrived; a frame is
  final once no later window contains it (about one window behind).
- `FrameEngine`: each frame is decoded once the next one has arrived (so a point added
  on the newest frame still joins it on time) and is final as soon as it is decoded: one
  frame of latency.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import torch
from torch import Tensor

from taptr.model.sliding_window import (
    FrameSource,
    QuerySet,
    TrackerState,
    add_points,
    decode_window,
    keep_points,
    start_state,
)
from taptr.model.taptr import TAPTR
from taptr.model.v3 import per_frame
from taptr.model.v3.taptr import TAPTRv3
from taptr.windows import window_ranges

Span = tuple[int, int]
"""First and last frame (inclusive) of a unit of decoding."""


class StreamEngine(Protocol):
    """What the online tracker asks of an engine; ``state`` is the engine's own state."""

    def start(self, queries: QuerySet, num_frames: int | None, dtype: torch.dtype) -> Any:
        """The driver state of a new stream."""
        ...

    def queries(self, state: Any) -> QuerySet:
        """The points the state tracks."""
        ...

    def add_points(self, state: Any, queries: QuerySet) -> None:
        """Appends points."""
        ...

    def keep_points(self, state: Any, keep: Tensor) -> None:
        """Keeps the points selected by the (N,) bool mask."""
        ...

    def next_span(self, state: Any, num_frames: int | None) -> Span | None:
        """The next unit to decode, or None when a declared stream has no more."""
        ...

    def remaining(self, state: Any, num_seen: int) -> list[Span]:
        """The units still to decode when the stream ends after ``num_seen`` frames."""
        ...

    def decode(self, state: Any, span: Span, frames: FrameSource) -> None:
        """Decodes one unit."""
        ...

    def final_bound(self, state: Any, num_seen: int, num_frames: int | None) -> int:
        """Frames before this index can no longer change."""
        ...

    def read(self, state: Any, first: int, bound: int) -> tuple[Tensor, Tensor]:
        """Last-layer positions (F, N, 2) normalised and logits (F, N) of frames first..bound−1."""
        ...

    def release(self, state: Any, before: int) -> None:
        """Forgets what frames before ``before`` needed."""
        ...


class WindowEngine:
    """The sliding-window driver, for TAPTR v1 and TAPTRv2."""

    def __init__(self, model: TAPTR) -> None:
        self.model = model

    def start(self, queries: QuerySet, num_frames: int | None, dtype: torch.dtype) -> TrackerState:
        """The driver state of a new stream."""
        return start_state(self.model, queries, num_frames, dtype)

    def queries(self, state: TrackerState) -> QuerySet:
        """The points the state tracks."""
        return state.queries

    def add_points(self, state: TrackerState, queries: QuerySet) -> None:
        """Appends points (`taptr.model.sliding_window.add_points`)."""
        add_points(self.model, state, queries)

    def keep_points(self, state: TrackerState, keep: Tensor) -> None:
        """Keeps the points selected by the (N,) bool mask."""
        keep_points(state, keep)

    def started(self, state: TrackerState) -> bool:
        """Whether anything was decoded yet."""
        return state.next_window > 0

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


@dataclass
class FrameStream:
    """TAPTRv3's driver state and the decoded frames not yet read.

    Attributes:
        tracker: the per-frame driver's state.
        decoded: per decoded frame not yet released, (N, 2) normalised positions and (N,)
            logits of the last layer.
    """

    tracker: per_frame.FrameState
    decoded: dict[int, tuple[Tensor, Tensor]] = field(default_factory=dict)


StepFor = Callable[[int | None, int | None], per_frame.DecoderStep | None]
"""Gives TAPTRv3's decoder step from a run's points and frames (None: not known yet)."""


class FrameEngine:
    """The per-frame driver, for TAPTRv3.

    Attributes:
        history_frames: the most frames held per point (None: the model's).
        step_for: gives the decoder step of a stream from its points and frames (None
            when not known yet; `taptr.api.predictor.Predictor.decoder_step`), or None
            for the model's own.
    """

    def __init__(
        self,
        model: TAPTRv3,
        history_frames: int | None = None,
        step_for: StepFor | None = None,
    ) -> None:
        self.model = model
        self.history_frames = history_frames
        self.step_for = step_for

    def start(self, queries: QuerySet, num_frames: int | None, dtype: torch.dtype) -> FrameStream:
        """The driver state of a new stream (its length does not matter)."""
        step = self.step_for(None, num_frames) if self.step_for else None
        state = per_frame.start_state(self.model, queries, dtype, self.history_frames, step=step)
        return FrameStream(state)

    def queries(self, state: FrameStream) -> QuerySet:
        """The points the state tracks."""
        return state.tracker.queries

    def add_points(self, state: FrameStream, queries: QuerySet) -> None:
        """Appends points; decoded frames not yet read get their start state."""
        per_frame.add_points(self.model, state.tracker, queries)
        start = per_frame.query_logits(queries, torch.float32)[0, :, :2].sigmoid()
        for frame, (positions, logits) in state.decoded.items():
            unwritten = per_frame.initial_visibility(self.model, queries, frame)[0, :, 1]
            state.decoded[frame] = (
                torch.cat((positions, start.to(positions))),
                torch.cat((logits, unwritten.to(logits))),
            )

    def keep_points(self, state: FrameStream, keep: Tensor) -> None:
        """Keeps the points selected by the (N,) bool mask."""
        per_frame.keep_points(state.tracker, keep)
        for frame, (positions, logits) in state.decoded.items():
            state.decoded[frame] = (positions[keep], logits[keep])

    def started(self, state: FrameStream) -> bool:
        """Whether anything was decoded yet."""
        return state.tracker.next_frame > 0

    def next_span(self, state: FrameStream, num_frames: int | None) -> Span | None:
        """The next frame, or None when a declared stream has no more."""
        frame = state.tracker.next_frame
        return None if num_frames is not None and frame >= num_frames else (frame, frame)

    def remaining(self, state: FrameStream, num_seen: int) -> list[Span]:
        """The frames still to decode when the stream ends after ``num_seen`` frames."""
        return [(frame, frame) for frame in range(state.tracker.next_frame, num_seen)]

    def decode(self, state: FrameStream, span: Span, frames: FrameSource) -> None:
        """Decodes one frame and keeps its last-layer outputs until they are read."""
        output = per_frame.decode_frame(self.model, state.tracker, frames)
        positions = output.positions[-1, 0, :, :2].sigmoid()
        state.decoded[output.frame] = (positions, output.visibility_logits[-1, 0, :, 1])

    def final_bound(self, state: FrameStream, num_seen: int, num_frames: int | None) -> int:
        """Every decoded frame is final."""
        return state.tracker.next_frame

    def read(self, state: FrameStream, first: int, bound: int) -> tuple[Tensor, Tensor]:
        """Last-layer positions (F, N, 2) normalised and logits (F, N) of frames first..bound−1."""
        frames = range(first, bound)
        positions = torch.stack([state.decoded[f][0] for f in frames])
        return positions, torch.stack([state.decoded[f][1] for f in frames])

    def release(self, state: FrameStream, before: int) -> None:
        """Forgets the outputs of frames before ``before``."""
        for frame in [f for f in state.decoded if f < before]:
            del state.decoded[frame]


def engine_for(
    model: TAPTR,
    history_frames: int | None = None,
    step_for: StepFor | None = None,
) -> StreamEngine:
    """The engine of ``model``'s family (TAPTRv3's: its history limit and step, `FrameEngine`)."""
    if isinstance(model, TAPTRv3):
        return FrameEngine(model, history_frames, step_for)
    return WindowEngine(model)
