"""The frame engine: TAPTRv3, decoded frame by frame.

A whole video is `taptr.model.v3.per_frame.run_frames`. A stream decodes each frame once
the next one has arrived (so that a point added on the newest frame still joins it on
time), and a frame is final as soon as it is decoded: one frame of latency. Each run asks
for its decoder step (`StepFor`: the runner's, `taptr.runtime.runner.Runner.decoder_step`);
a step that replays a capture decodes the points padded to its bucket, which never show
in what a run returns.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

from taptr.model.frame_source import FrameSource, Span
from taptr.model.trajectory import QuerySet, TrackOutput, first_points
from taptr.model.v3 import per_frame
from taptr.model.v3.taptr import TAPTRv3
from taptr.runtime.capture_buckets import pad_points, points_bucket
from taptr.runtime.step_capture import StepCapture
from taptr.types import OnStep

StepFor = Callable[[int | None, int | None], StepCapture | None]
"""Gives a run's decoder step from its points and frames (None: not known, a stream);
None from it: the model's own decoder."""


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


class FrameEngine:
    """Runs TAPTRv3.

    Args:
        model: the network.
        dtype: floating dtype of the positions and content.
        history_frames: the most frames held per point (None: the model's).
        step_for: gives each run's decoder step; None: the model's decoder always.
    """

    unit = "frame"

    def __init__(
        self,
        model: TAPTRv3,
        dtype: torch.dtype,
        history_frames: int | None = None,
        step_for: StepFor | None = None,
    ) -> None:
        self.model = model
        self.dtype = dtype
        self.history_frames = history_frames
        self.step_for = step_for

    def steps(self, num_frames: int) -> int:
        """How many frames a video of ``num_frames`` decodes (`run`'s ``on_step`` calls)."""
        return num_frames

    def run(
        self, queries: QuerySet, num_frames: int, frames: FrameSource, on_step: OnStep = None
    ) -> TrackOutput:
        """Tracks the queries through a whole video, frame by frame (`Engine.run`)."""
        points = queries.start_frames.shape[1]
        step = self.step_for(points, num_frames) if self.step_for else None
        decoded = queries
        if step is not None and step.captured:  # nearby point counts replay one capture
            decoded = pad_points(queries, points_bucket(points))
        output = per_frame.run_frames(
            self.model,
            decoded,
            num_frames,
            frames,
            self.dtype,
            on_step,
            history_frames=self.history_frames,
            step=step,
        )
        return output if decoded is queries else first_points(output, points)

    def start(self, queries: QuerySet, num_frames: int | None) -> FrameStream:
        """The driver state of a new stream (its length only decides about capturing)."""
        step = self.step_for(None, num_frames) if self.step_for else None
        state = per_frame.start_state(
            self.model, queries, self.dtype, self.history_frames, step=step
        )
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
