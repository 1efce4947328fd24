"""Streaming TAPTRv3 over its ONNX export without torch: frames in as they arrive.

`OnnxOnlineTracker` is `taptr.api.online.OnlineTracker` for the exported graphs: each
frame is decoded once the next one has arrived, so that a point added on the newest frame
still joins it, and is returned as soon as it is decoded (one frame of latency). Points
are added (on frames not yet decoded) and removed at any time; who is who among them, and
the support each brings or takes along, is `taptr.task.stream_points`'s bookkeeping, the
same as the PyTorch stream's. All state lives in the `OnnxStream` the caller holds.
Adding points checks the stream's estimated memory first (`taptr.onnx.graph_memory`).

Shapes: F frames, N user points, N_t points the model tracks.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from taptr.onnx.frame_loop import (
    FrameMemory,
    LoopState,
    add_points,
    decode_frame,
    keep_points,
    start_state,
)
from taptr.onnx.graph_memory import check_run_memory
from taptr.onnx.video_tracker import OnnxTracker
from taptr.task.pixel_queries import normalised, on_own_frames, pixel_queries, pixel_scale
from taptr.task.pixel_queries import visible as visible_where
from taptr.task.resizing import resize_frames
from taptr.task.results import FrameCountError, StreamUpdate
from taptr.task.stream_points import StreamPoints
from taptr.task.support_schemes import SupportPoints


@dataclass
class OnnxStream:
    """Everything the online tracker knows about one stream.

    Attributes:
        loop: the frame loop's state (every point the model tracks).
        num_frames: declared stream length, or None.
        frame_size: (H, W) of the input frames.
        waiting: resized frames (3, H_m, W_m) that arrived and are not decoded yet.
        num_seen: frames received so far.
        points: the user's points, their identifiers and the support around them.
    """

    loop: LoopState
    num_frames: int | None
    frame_size: tuple[int, int] | None
    waiting: dict[int, np.ndarray] = field(default_factory=dict)
    num_seen: int = 0
    points: StreamPoints = field(default_factory=StreamPoints)

    @property
    def point_ids(self) -> list[int]:
        """Identifier of each user point, in order."""
        return self.points.point_ids

    @property
    def queries(self) -> np.ndarray:
        """(N, 3) float32 (t, x, y) pixels of the user's points."""
        return self.points.queries


def checked_frames(frames: Any) -> np.ndarray:
    """uint8 frames as (F, H, W, 3).

    Raises:
        ValueError: not a numpy array of uint8 RGB frames.
    """
    if not isinstance(frames, np.ndarray):
        kind = type(frames).__name__
        raise ValueError(
            f"frames must be a uint8 numpy array (F, H, W, 3) or (H, W, 3), got {kind}"
        )
    chunk = frames[None] if frames.ndim == 3 else frames
    if chunk.ndim != 4 or chunk.shape[-1] != 3 or chunk.dtype != np.uint8 or not len(chunk):
        raise ValueError(f"frames must be uint8 (F, H, W, 3), got {chunk.dtype} {chunk.shape}")
    return chunk


class OnnxOnlineTracker:
    """Streaming front end of an `OnnxTracker` (one stream at a time, forward in time)."""

    def __init__(self, tracker: OnnxTracker) -> None:
        self.tracker = tracker
        self.graphs = tracker.graphs
        self.manifest = tracker.manifest

    def start(
        self, num_frames: int | None = None, frame_size: tuple[int, int] | None = None
    ) -> OnnxStream:
        """A new, empty stream.

        Args:
            num_frames: total length, when known.
            frame_size: (H, W) of the frames, needed to add queries before the first frame.
        """
        loop = start_state(self.manifest, self.tracker.history_frames)
        return OnnxStream(loop, num_frames, frame_size)

    def add_queries(self, stream: OnnxStream, queries: Any) -> list[int]:
        """Adds points given as (N, 3) (t, x, y) pixels; returns their identifiers.

        Raises:
            ValueError: the frame size is unknown, a query is invalid, its frame is
                already decoded (t must be at least ``stream.loop.next_frame``), or the
                stream's points would need more memory than the budget.
        """
        if stream.frame_size is None:
            raise ValueError(
                "the frame size is unknown: feed a frame first or pass frame_size to start()"
            )
        height, width = stream.frame_size
        new = pixel_queries(queries, stream.num_frames, height, width)
        if (new[:, 0] < stream.loop.next_frame).any():
            raise ValueError(f"query frames must come after frame {stream.loop.next_frame - 1}")
        starts, xy = new[:, 0].astype(np.int64), normalised(new[:, 1:], height, width)
        self._check_memory(stream, starts, xy)
        add_points(self.manifest, stream.loop, starts, xy)
        ids = stream.points.add_queries(new)
        pattern = self.tracker.support_pattern
        self._add_support(stream, stream.points.support_added(ids, starts, xy, pattern))
        return ids

    def remove_queries(self, stream: OnnxStream, ids: list[int]) -> None:
        """Stops tracking the given points; their local support points leave with them.

        Raises:
            ValueError: unknown identifiers.
        """
        keep_points(stream.loop, stream.points.remove(ids))

    def step(self, stream: OnnxStream, frames: Any) -> StreamUpdate:
        """Feeds uint8 frames (F, H, W, 3) or one (H, W, 3); returns the frames now final.

        Raises:
            ValueError: another frame size than before, or not uint8 RGB frames.
            FrameCountError: more frames than declared.
        """
        chunk = checked_frames(frames)
        size = (chunk.shape[1], chunk.shape[2])
        if stream.frame_size is None:
            stream.frame_size = size
        elif size != stream.frame_size:
            raise ValueError(f"frame size changed from {stream.frame_size} to {size}")
        declared = stream.num_frames
        if declared is not None and stream.num_seen + len(chunk) > declared:
            seen = stream.num_seen + len(chunk)
            raise FrameCountError(
                f"more frames than the declared {declared}", seen=seen, declared=declared
            )
        resized = resize_frames(chunk, self.manifest.input_size, self.manifest.resize)
        for offset, frame in enumerate(resized):
            stream.waiting[stream.num_seen + offset] = frame
        stream.num_seen += len(chunk)
        last = stream.num_seen - 2  # a frame is decoded once the next one has arrived
        if declared is not None:
            last = min(last, declared - 1)
        return self._decode_until(stream, last)

    def finish(self, stream: OnnxStream) -> StreamUpdate:
        """Ends the stream: decodes and returns every remaining frame.

        Raises:
            ValueError: a stream without frames.
            FrameCountError: fewer frames than declared.
        """
        if stream.num_seen == 0:
            raise ValueError("the stream has no frames")
        if stream.num_frames is not None and stream.num_seen != stream.num_frames:
            raise FrameCountError(
                f"the stream ended after {stream.num_seen} of {stream.num_frames} declared frames",
                seen=stream.num_seen,
                declared=stream.num_frames,
            )
        return self._decode_until(stream, stream.num_seen - 1)

    def _check_memory(self, stream: OnnxStream, starts: np.ndarray, xy: np.ndarray) -> None:
        """Refuses points whose stream would need more than the memory budget."""
        pattern, scheme = self.tracker.support_pattern, stream.points.scheme
        if scheme is None:  # drawn on the first frame, from every point known then
            users = len(stream.point_ids) + len(starts)
            total = users + self.tracker.chosen_support(users).count(users, pattern)
        else:
            brought = len(scheme.added(starts, xy, pattern).parents)
            total = len(stream.loop.start_frames) + len(starts) + brought
        limit, weights = self.tracker.history_frames, self.tracker.graph_bytes
        check_run_memory(self.manifest, total, stream.num_frames, limit, weights)

    def _decode_until(self, stream: OnnxStream, last: int) -> StreamUpdate:
        """Decodes frames up to ``last`` and returns them for the user's points."""
        first = stream.loop.next_frame
        memory = FrameMemory(self.graphs, lambda frame: stream.waiting[frame])
        positions, logits = [], []
        while stream.loop.next_frame <= last:
            if stream.points.scheme is None:
                self._draw_support(stream)
            frame = stream.loop.next_frame
            result = decode_frame(self.graphs, stream.loop, memory)
            del stream.waiting[frame]
            users = stream.points.users
            positions.append(result.positions[users])
            logits.append(result.visibility_logits[users, 1])
        return self._update(stream, first, positions, logits)

    def _update(
        self, stream: OnnxStream, first: int, positions: list[np.ndarray], logits: list[np.ndarray]
    ) -> StreamUpdate:
        """The decoded frames in pixels, each query on its own frame."""
        height, width = stream.frame_size or (1, 1)
        count = len(stream.point_ids)
        tracks = np.stack(positions) * pixel_scale(height, width) if positions else None
        tracks, values = on_own_frames(
            tracks if tracks is not None else np.zeros((0, count, 2), np.float32),
            np.stack(logits) if logits else np.zeros((0, count), np.float32),
            stream.queries,
            first,
            hide_earlier=True,  # a stream only tracks forward in time
        )
        seen = visible_where(values, self.tracker.visibility_threshold)
        return StreamUpdate(first, tracks, seen, values, list(stream.point_ids))

    def _draw_support(self, stream: OnnxStream) -> None:
        """Draws the support from the points known now (before the first frame)."""
        height, width = stream.frame_size or (1, 1)
        scheme = self.tracker.chosen_support(len(stream.point_ids))
        xy = normalised(stream.queries[:, 1:], height, width)
        self._add_support(
            stream, stream.points.draw_support(scheme, self.tracker.support_pattern, xy)
        )

    def _add_support(self, stream: OnnxStream, support: SupportPoints) -> None:
        """Adds support points (never returned) to the loop and the bookkeeping."""
        if len(support.parents):
            add_points(self.manifest, stream.loop, support.start_frames, support.positions)
            stream.points.add_support(support.parents)
