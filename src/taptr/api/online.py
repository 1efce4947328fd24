"""Online tracking: feed frames as they arrive, add and remove points at any time.

All state lives in an explicit `StreamState` that the caller holds and passes back in. The
model runs through the predictor's `taptr.runtime.runner.Runner`, as for a whole video:
frames are prepared as they arrive, encoded by the runner's frame cache when the first
window reads them (`taptr.runtime.frames.StreamFrames`), and dropped once no window can read
them, so memory is bounded by the window, not the stream.

A window is decoded once a frame after its last frame has arrived (so that a point added
on the newest frame still joins it), and a frame's tracks are returned once no later
window can change them: at most about one window (8 frames) behind the newest frame.
TAPTRv3 decodes frame by frame: each frame is decoded, and returned, once the next one
has arrived (`taptr.runtime.engines`).

Context or support points (`Predictor.with_support`) are drawn when the first window is
decoded, from the points known then, and are never returned; points added later join them.

The result equals the offline `Predictor.track` on the same frames and queries, given
that every query is added before a window containing its query frame is decoded (always
true for queries on the newest frame; with context points, before the first window), when
the stream is shorter than 48 frames or its length is declared in `OnlineTracker.start`.
For longer undeclared streams the official long-video rule (content handed to future
frames only after every ⌊T / 24⌋-th window) is unknowable in advance, and the content is
handed over after every window instead.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from taptr.api.inputs import query_tensor, video_tensor
from taptr.api.predictor import Predictor
from taptr.api.queries import model_queries, on_own_frames
from taptr.api.support import as_query_set, pattern_for
from taptr.geometry import normalized_to_pixels
from taptr.model.trajectory import QuerySet, TrackerState
from taptr.runtime.engines import Engine
from taptr.runtime.frame_engine import FrameStream
from taptr.runtime.frames import StreamFrames
from taptr.task.results import FrameCountError as FrameCountError  # re-exported: public
from taptr.task.results import StreamUpdate as StreamUpdate  # re-exported: public
from taptr.task.stream_points import StreamPoints


@dataclass
class StreamState:
    """Everything an online tracker knows about one stream.

    Attributes:
        tracker: the driver's state (points, trajectories, next window or frame).
        num_frames: declared stream length, or None.
        frame_size: (H, W) of the input frames, set by the first frames or by `start`.
        num_seen: frames received so far.
        emitted: frames [0, emitted) have been returned.
        last_decoded: last frame of the last decoded window (−1 before the first).
        encoded: the frames still needed (prepared ones waiting for their first window and
            the encoded window the frame cache keeps); ``len`` counts them.
        points: the user's points, their identifiers and the support around them
            (`taptr.task.stream_points`); ``queries``, ``point_ids``, ``is_context``,
            ``support`` and ``support_of`` read it.
        context_added: whether the context or support points have been drawn.
    """

    tracker: TrackerState | FrameStream
    num_frames: int | None
    frame_size: tuple[int, int] | None
    encoded: StreamFrames
    num_seen: int = 0
    emitted: int = 0
    last_decoded: int = -1
    points: StreamPoints = field(default_factory=StreamPoints)
    context_added: bool = False

    @property
    def queries(self) -> Tensor:
        """(N, 3) float32 (t, x, y) pixels of the current user points."""
        return torch.from_numpy(self.points.queries)

    @property
    def point_ids(self) -> list[int]:
        """Identifier of each current user point, in order."""
        return self.points.point_ids

    @property
    def is_context(self) -> Tensor:
        """(N_t,) bool over the tracker's points: True for context or support points."""
        return torch.from_numpy(self.points.is_support)

    @property
    def support_of(self) -> Tensor:
        """(N_t,) int64: the user point a local support point surrounds, else −1."""
        return torch.from_numpy(self.points.support_of)

    @property
    def support(self) -> str | None:
        """The support scheme's name once drawn (`Predictor.support_scheme`)."""
        scheme = self.points.scheme
        return None if scheme is None else scheme.name


class OnlineTracker:
    """Streaming front end of a `Predictor` (one video at a time, forward in time).

    Pixels, queries and support points are the predictor's; the model runs through the
    predictor's runner (`Predictor.runner`), whose engine decodes the stream unit by unit.
    """

    def __init__(self, predictor: Predictor) -> None:
        self.predictor = predictor
        self.runner = predictor.runner
        self.engine: Engine = predictor.runner.engine

    def start(
        self, num_frames: int | None = None, frame_size: tuple[int, int] | None = None
    ) -> StreamState:
        """A new, empty stream.

        Args:
            num_frames: total length, when known (makes long streams equal to offline).
            frame_size: (H, W) of the frames, needed to add queries before the first frame.
        """
        device, dtype = self.runner.device, self.runner.dtype
        empty = model_queries(torch.zeros(0, 3), 1, 1, device, dtype)  # no points: any size
        tracker = self.engine.start(empty, num_frames)
        return StreamState(tracker, num_frames, frame_size, self.runner.stream_frames())

    def add_queries(self, state: StreamState, queries: np.ndarray | Tensor) -> list[int]:
        """Adds points given as (N, 3) (t, x, y) pixels; returns their identifiers.

        Raises:
            ValueError: the frame size is unknown, a position lies outside the frame, or a
                query frame is already decoded (t must exceed ``state.last_decoded``).
        """
        if state.frame_size is None:
            raise ValueError(
                "the frame size is unknown: feed a frame first or pass frame_size to start()"
            )
        height, width = state.frame_size
        new = query_tensor(queries, 1, state.num_frames, height, width)[0]  # (N, 3)
        if bool((new[:, 0] <= state.last_decoded).any()):
            raise ValueError(f"query frames must come after frame {state.last_decoded}")
        points = model_queries(new, height, width, self.runner.device, self.runner.dtype)
        self.engine.add_points(state.tracker, points)
        ids = state.points.add_queries(new.numpy())
        starts = points.start_frames[0].cpu().numpy()
        support = state.points.support_added(
            ids, starts, points.positions[0].cpu().numpy(), pattern_for(points)
        )
        if len(support.parents):  # the support of points added after it was drawn
            self._add_support_points(state, as_query_set(support, points), support.parents)
        return ids

    def remove_queries(self, state: StreamState, ids: list[int]) -> None:
        """Stops tracking the given points and the support around them.

        Context and grid points stay; local support points leave with their point.

        Raises:
            ValueError: unknown identifiers.
        """
        keep = torch.from_numpy(state.points.remove(ids))
        self.engine.keep_points(state.tracker, keep.to(self.runner.device))

    @torch.no_grad()
    def step(self, state: StreamState, frames: np.ndarray | Tensor) -> StreamUpdate:
        """Feeds frames and returns the tracks of every frame that became final.

        Args:
            state: the stream (updated in place).
            frames: uint8 numpy (F, H, W, 3) or (H, W, 3) for one frame, or a torch
                tensor (F, 3, H, W) of uint8 or floats in [0, 1].
        """
        chunk = self._frames(frames)
        size = (chunk.shape[-2], chunk.shape[-1])
        if state.frame_size is None:
            state.frame_size = size
        elif size != state.frame_size:
            raise ValueError(f"frame size changed from {state.frame_size} to {size}")
        if state.num_frames is not None and state.num_seen + chunk.shape[0] > state.num_frames:
            raise FrameCountError(
                f"more frames than the declared {state.num_frames}",
                seen=state.num_seen + chunk.shape[0],
                declared=state.num_frames,
            )
        state.encoded.add(state.num_seen, self.predictor.prepare(chunk))
        state.num_seen += chunk.shape[0]
        while True:
            span = self.engine.next_span(state.tracker, state.num_frames)
            if span is None or span[1] >= state.num_seen - 1:
                break
            self._decode(state, *span)
        bound = self.engine.final_bound(state.tracker, state.num_seen, state.num_frames)
        return self._emit(state, bound)

    @torch.no_grad()
    def finish(self, state: StreamState) -> StreamUpdate:
        """Ends the stream: decodes the remaining windows and returns every remaining frame."""
        if state.num_seen == 0:
            raise ValueError("the stream has no frames")
        if state.num_frames is not None and state.num_seen != state.num_frames:
            raise FrameCountError(
                f"the stream ended after {state.num_seen} of {state.num_frames} declared frames",
                seen=state.num_seen,
                declared=state.num_frames,
            )
        for first, last in self.engine.remaining(state.tracker, state.num_seen):
            self._decode(state, first, last)
        return self._emit(state, state.num_seen)

    def _frames(self, frames: np.ndarray | Tensor) -> Tensor:
        if isinstance(frames, np.ndarray):
            return video_tensor(frames[None] if frames.ndim == 3 else frames)[0]
        return video_tensor(frames[None])[0]

    def _add_context(self, state: StreamState) -> None:
        """Draws the context or support points from the points known now (first unit)."""
        state.context_added = True
        known = self.engine.queries(state.tracker)
        scheme = self.predictor.chosen_support(known.start_frames.shape[1])
        pattern = pattern_for(known, self.predictor.context_points)
        xy = known.positions[0].cpu().numpy()
        support = state.points.draw_support(scheme, pattern, xy, caller_draws=True)
        if len(support.parents):
            self._add_support_points(state, as_query_set(support, known), support.parents)
        if not scheme.drawn:
            return
        padded = self.predictor.with_support(known, state.num_frames, scheme.name)
        count = padded.start_frames.shape[1] - known.start_frames.shape[1]
        if count:  # seeded context points, drawn per stream; they surround no point
            drawn = QuerySet(*(column[:, -count:] for column in padded))
            self._add_support_points(state, drawn, np.full(count, -1, np.int64))

    def _add_support_points(
        self, state: StreamState, points: QuerySet, parents: np.ndarray
    ) -> None:
        """Adds context or support points, never returned; ``parents`` (K,) their points."""
        self.engine.add_points(state.tracker, points)
        state.points.add_support(parents)

    def _decode(self, state: StreamState, first: int, last: int) -> None:
        if not state.context_added:
            self._add_context(state)
        self.runner.decode(state.tracker, (first, last), state.encoded)
        state.last_decoded = last

    def _emit(self, state: StreamState, bound: int) -> StreamUpdate:
        first = state.emitted
        height, width = state.frame_size or (1, 1)
        if bound > first:
            positions, logits = self.engine.read(state.tracker, first, bound)
            users = ~state.is_context.to(positions.device)
            positions, logits = positions[:, users], logits[:, users]
        else:
            positions = torch.zeros(0, len(state.point_ids), 2)
            logits = torch.zeros(0, len(state.point_ids))
        tracks, logits = on_own_frames(
            normalized_to_pixels(positions.float().cpu(), height, width),
            logits.float().cpu(),
            state.queries,
            first,
            hide_earlier=True,  # a stream only tracks forward in time
        )
        state.emitted = max(bound, first)
        self._release(state, state.emitted)
        visibility = logits.sigmoid() > self.predictor.visibility_threshold
        return StreamUpdate(first, tracks, visibility, logits, list(state.point_ids))

    def _release(self, state: StreamState, before: int) -> None:
        state.encoded.release(before)
        self.engine.release(state.tracker, before)
