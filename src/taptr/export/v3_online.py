"""Streaming TAPTRv3 over its ONNX export without torch: frames in as they arrive.

`OnnxOnlineTracker` is `taptr.api.online.OnlineTracker`'s twin for TAPTRv3 (its
``FrameEngine``): each frame is decoded once the next one has arrived, so that a point
added on the newest frame still joins it, and is returned as soon as it is decoded (one
frame of latency). Points are added (on frames not yet decoded) and removed at any time;
support points are drawn when the first frame is decoded, from the points known then, and
points added later bring their own local points, which leave with them. All state lives
in the `OnnxStream` the caller holds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from taptr.export.v3_loop import (
    FrameMemory,
    LoopState,
    add_points,
    decode_frame,
    keep_points,
    start_state,
)
from taptr.export.v3_queries import (
    local_points,
    normalised,
    on_own_frames,
    pixel_queries,
    pixel_scale,
    support_points,
    support_scheme,
    visible,
)
from taptr.export.v3_resize import resize_frames
from taptr.export.v3_tracker import OnnxTracker


class FrameCountError(ValueError):
    """A stream brought more or fewer frames than `OnnxOnlineTracker.start` was told."""


@dataclass
class OnnxStream:
    """Everything the online tracker knows about one stream.

    Attributes:
        loop: the frame loop's state (every point the model tracks).
        num_frames: declared stream length, or None.
        frame_size: (H, W) of the input frames.
        waiting: resized frames (3, H_m, W_m) that arrived and are not decoded yet.
        num_seen: frames received so far.
        queries: (N, 3) float32 (t, x, y) pixels of the user's points.
        point_ids: identifier of each user point, in order.
        next_id: identifier of the next point added.
        is_support: (N_t,) bool over the loop's points: True for support points.
        support: the support scheme, once drawn (before the first frame is decoded).
        support_of: (N_t,) int64: the user point a local support point surrounds, else −1.
    """

    loop: LoopState
    num_frames: int | None
    frame_size: tuple[int, int] | None
    waiting: dict[int, np.ndarray] = field(default_factory=dict)
    num_seen: int = 0
    queries: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    point_ids: list[int] = field(default_factory=list)
    next_id: int = 0
    is_support: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    support: str | None = None
    support_of: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


class StreamUpdate(NamedTuple):
    """Tracks of the frames that became final.

    Attributes:
        first_frame: index of the first returned frame.
        tracks: (F, N, 2) float32 (x, y) pixels of the input frames.
        visibility: (F, N) bool.
        visibility_logits: (F, N) float32; −inf before a point's query frame.
        point_ids: identifier of each of the N points.
    """

    first_frame: int
    tracks: np.ndarray
    visibility: np.ndarray
    visibility_logits: np.ndarray
    point_ids: list[int]


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
            ValueError: the frame size is unknown, a query is invalid, or its frame is
                already decoded (t must be at least ``stream.loop.next_frame``).
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
        add_points(self.manifest, stream.loop, starts, xy)
        ids = list(range(stream.next_id, stream.next_id + len(new)))
        stream.next_id += len(new)
        stream.point_ids += ids
        stream.queries = np.concatenate((stream.queries, new))
        stream.is_support = np.concatenate((stream.is_support, np.zeros(len(ids), bool)))
        stream.support_of = np.concatenate((stream.support_of, np.full(len(ids), -1)))
        if stream.support == "local_and_grid":  # the support of points added later
            local_starts, local_xy = local_points(self.manifest.support, starts, xy)
            parents = np.repeat(ids, len(self.manifest.support.local_offsets))
            self._add_support(stream, local_starts, local_xy, parents)
        return ids

    def remove_queries(self, stream: OnnxStream, ids: list[int]) -> None:
        """Stops tracking the given points; their local support points leave with them.

        Raises:
            ValueError: unknown identifiers.
        """
        removed = set(ids)
        unknown = sorted(removed.difference(stream.point_ids))
        if unknown:
            raise ValueError(f"unknown point ids: {unknown[:10]}")
        keep = np.array([pid not in removed for pid in stream.point_ids], bool)
        gone = np.array(sorted(removed), np.int64)
        keep_all = stream.is_support & ~np.isin(stream.support_of, gone)
        keep_all[~stream.is_support] = keep
        keep_points(stream.loop, keep_all)
        stream.is_support = stream.is_support[keep_all]
        stream.support_of = stream.support_of[keep_all]
        stream.queries = stream.queries[keep]
        stream.point_ids = [pid for pid in stream.point_ids if pid not in removed]

    def step(self, stream: OnnxStream, frames: np.ndarray) -> StreamUpdate:
        """Feeds uint8 frames (F, H, W, 3) or one (H, W, 3); returns the frames now final.

        Raises:
            ValueError: another frame size than before, or not uint8 RGB frames.
            FrameCountError: more frames than declared.
        """
        chunk = frames[None] if frames.ndim == 3 else frames
        if chunk.ndim != 4 or chunk.shape[-1] != 3 or chunk.dtype != np.uint8:
            raise ValueError(f"frames must be uint8 (F, H, W, 3), got {chunk.dtype} {chunk.shape}")
        size = (chunk.shape[1], chunk.shape[2])
        if stream.frame_size is None:
            stream.frame_size = size
        elif size != stream.frame_size:
            raise ValueError(f"frame size changed from {stream.frame_size} to {size}")
        declared = stream.num_frames
        if declared is not None and stream.num_seen + len(chunk) > declared:
            raise FrameCountError(f"more frames than the declared {declared}")
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
                f"the stream ended after {stream.num_seen} of {stream.num_frames} declared frames"
            )
        return self._decode_until(stream, stream.num_seen - 1)

    def _decode_until(self, stream: OnnxStream, last: int) -> StreamUpdate:
        """Decodes frames up to ``last`` and returns them for the user's points."""
        first = stream.loop.next_frame
        memory = FrameMemory(self.graphs, lambda frame: stream.waiting[frame])
        positions, logits = [], []
        while stream.loop.next_frame <= last:
            if stream.support is None:
                self._add_support_points(stream)
            frame = stream.loop.next_frame
            result = decode_frame(self.graphs, stream.loop, memory)
            del stream.waiting[frame]
            users = ~stream.is_support
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
        seen = visible(values, self.tracker.visibility_threshold)
        return StreamUpdate(first, tracks, seen, values, list(stream.point_ids))

    def _add_support_points(self, stream: OnnxStream) -> None:
        """Draws the support from the points known now (before the first frame)."""
        known = len(stream.point_ids)
        rule = self.manifest.support
        stream.support = support_scheme(rule, known, self.tracker.support_points)
        height, width = stream.frame_size or (1, 1)
        starts = stream.queries[:, 0].astype(np.int64)
        xy = normalised(stream.queries[:, 1:], height, width)
        extra_starts, extra_xy = support_points(rule, stream.support, starts, xy)
        parents = np.full(len(extra_starts), -1, np.int64)
        if stream.support == "local_and_grid":  # the local points of each point, in order
            local = np.repeat(stream.point_ids, len(rule.local_offsets))
            parents[: len(local)] = local
        self._add_support(stream, extra_starts, extra_xy, parents)

    def _add_support(
        self, stream: OnnxStream, starts: np.ndarray, xy: np.ndarray, parents: np.ndarray
    ) -> None:
        """Adds support points (never returned); ``parents`` (K,): the point each surrounds."""
        add_points(self.manifest, stream.loop, starts, xy)
        stream.is_support = np.concatenate((stream.is_support, np.ones(len(starts), bool)))
        stream.support_of = np.concatenate((stream.support_of, parents.astype(np.int64)))
