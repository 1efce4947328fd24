"""The tracker actor of a corpus: one `Predictor` per actor, one video per call.

Ray Data calls `VideoTracker` with batches of one probed row (`taptr.corpus.probe`). The
frames stream from the decoder through `taptr.api.streaming.track_frames` (a reader thread
decodes a few frames ahead while the model runs), so an actor's memory stays flat in the
video's length; only the tracks (T × N) are held. The video's rows are then written
atomically (`taptr.corpus.results`).

Before tracking a video the actor records an attempt (``_attempts/``); a video whose
earlier attempts all ended with the actor's death (killed, out of memory) is recorded as
failed once it has had ``max_attempts`` of them, instead of being tried again.

Testing hook: ``TAPTR_CORPUS_KILL="VIDEO_ID:N[,VIDEO_ID:N...]"`` makes an actor exit
abruptly (``os._exit``, as the OOM killer would end it) in the middle of that video's first
N attempts.
"""

from __future__ import annotations

import os
import queue
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from taptr.corpus.probe import one_line
from taptr.corpus.results import ResultLayout, VideoTracks

if TYPE_CHECKING:
    from taptr.api.predictor import Predictor

KILL_VARIABLE = "TAPTR_CORPUS_KILL"
"""The fault-injection hook's environment variable (tests only)."""

READ_AHEAD = 8
"""Frames the reader thread decodes ahead of the tracker."""

OUTCOME_FIELDS = ("video_id", "status", "error", "frames", "points", "seconds", "attempts")
"""Columns of what an actor returns per video (``status``: ``done`` or ``failed``;
``attempts``: tracking attempts started, more than 1 after its worker died)."""


@dataclass(frozen=True)
class TrackOptions:
    """How each video is tracked and recorded.

    Attributes:
        out: the output folder (`ResultLayout`).
        max_attempts: attempts at a video before its worker's deaths make it a failure.
        max_frames: track at most this many frames of each video (None: all).
        backward: also track before each query frame (the file is read twice).
    """

    out: str
    max_attempts: int = 3
    max_frames: int | None = None
    backward: bool = False


class VideoTracker:
    """A Ray Data callable class holding one predictor.

    Args:
        make_predictor: builds the predictor (called once, in the actor).
        options: how to track and where to write.
        threads: torch threads for CPU actors (None leaves torch's default).
    """

    def __init__(
        self,
        make_predictor: Callable[[], Predictor],
        options: TrackOptions,
        threads: int | None = None,
    ) -> None:
        if threads is not None:
            import torch

            torch.set_num_threads(threads)
        self.predictor = make_predictor()
        self.options = options
        self.layout = ResultLayout(options.out)

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, list]:
        """Tracks the batch's videos; one outcome row each (`OUTCOME_FIELDS`)."""
        count = len(batch["video_id"])
        outcomes = [self.track_one({k: v[i] for k, v in batch.items()}) for i in range(count)]
        return {name: [outcome[name] for outcome in outcomes] for name in OUTCOME_FIELDS}

    def track_one(self, row: dict[str, Any]) -> dict[str, Any]:
        """Tracks one probed row, or records why it cannot be; returns its outcome."""
        started = time.perf_counter()
        key, digest = str(row["key"]), str(row["digest"])
        earlier = 0
        error = str(row["error"])
        if not error:
            earlier = self.layout.start_attempt(key, digest)
            if earlier >= self.options.max_attempts:
                error = f"its worker died in each of {earlier} attempts (killed or out of memory)"
        if not error:
            try:
                video = self._track(row, attempt=earlier + 1)
            except Exception as failure:  # a bad video must not stop the others
                error = one_line(failure)
            else:
                self.layout.write_tracks(key, video)
                shape = video.visibility.shape
                return _outcome(row, "done", "", shape, started, earlier + 1)
        attempts = earlier if earlier >= self.options.max_attempts else earlier + 1
        self.layout.write_failure(
            key, str(row["video_id"]), str(row["path"]), error, attempts, digest
        )
        return _outcome(row, "failed", error, (0, 0), started, attempts)

    def _track(self, row: dict[str, Any], attempt: int) -> VideoTracks:
        from taptr.api.online import FrameCountError

        path = str(row["path"])
        queries = np.frombuffer(row["query_array"], np.float32).reshape(-1, 3).copy()
        declared = int(row["num_frames"]) or None
        if declared is not None and self.options.max_frames is not None:
            declared = min(declared, self.options.max_frames)
        tracks = visibility = None
        if declared is not None:
            try:
                tracks, visibility = self._stream(row, queries, declared, attempt)
            except FrameCountError:  # the container's frame count was wrong
                tracks = None
        if tracks is None or visibility is None:
            tracks, visibility = self._in_memory(path, queries)
        return VideoTracks(
            video_id=str(row["video_id"]),
            path=path,
            queries=queries,
            tracks=tracks,
            visibility=visibility,
            size=(int(row["height"]), int(row["width"])),
            fps=float(row["fps"]) or None,
            model=str(self.predictor.source),
            digest=str(row["digest"]),
        )

    def _stream(
        self, row: dict[str, Any], queries: np.ndarray, num_frames: int, attempt: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Tracks frame by frame: (T, N, 2) tracks and (T, N) visibility."""
        from taptr.api.streaming import track_frames, track_frames_both_ways
        from taptr.io.reverse_frames import iter_frames_reversed
        from taptr.io.video import iter_frames

        path, limit = str(row["path"]), self.options.max_frames
        doomed = _doomed(str(row["video_id"]), attempt)

        def read() -> Iterator[np.ndarray]:
            return _read_ahead(_dying(iter_frames(path, max_frames=limit), doomed))

        if self.options.backward:
            batches = track_frames_both_ways(
                self.predictor,
                read,
                lambda: iter_frames_reversed(path, max_frames=limit),
                queries,
                num_frames=num_frames,
            )
        else:
            batches = track_frames(self.predictor, read(), queries, num_frames=num_frames)
        parts = [(batch.tracks, batch.visibility) for batch in batches]
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])

    def _in_memory(self, path: str, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For containers that do not state their length: the whole video at once."""
        from taptr.io.video import read_video

        frames = read_video(path, max_frames=self.options.max_frames)
        result = self.predictor.track(frames, queries, backward=self.options.backward)
        return result.tracks[0].numpy(), result.visibility[0].numpy()


def _outcome(
    row: dict[str, Any],
    status: str,
    error: str,
    shape: tuple[int, int],
    started: float,
    attempts: int,
) -> dict[str, Any]:
    return {
        "video_id": str(row["video_id"]),
        "status": status,
        "error": error,
        "frames": int(shape[0]),
        "points": int(shape[1]),
        "seconds": time.perf_counter() - started,
        "attempts": attempts,
    }


def _doomed(video_id: str, attempt: int) -> bool:
    """Whether the testing hook asks this attempt at ``video_id`` to die."""
    for entry in filter(None, os.environ.get(KILL_VARIABLE, "").split(",")):
        name, _, times = entry.strip().rpartition(":")
        if name == video_id and attempt <= int(times):
            return True
    return False


def _dying(frames: Iterator[np.ndarray], doomed: bool) -> Iterator[np.ndarray]:
    """``frames``, or (testing hook) the first two of them and then the process's end."""
    for index, frame in enumerate(frames):
        if doomed and index == 2:
            os._exit(1)  # as abrupt as a SIGKILL: no cleanup, no exception
        yield frame


def _read_ahead(frames: Iterator[np.ndarray], depth: int = READ_AHEAD) -> Iterator[np.ndarray]:
    """``frames`` decoded in a thread, at most ``depth`` ahead (decoding overlaps tracking).

    An error of the decoder is raised here, in the consumer, where it happened in order.
    """
    ahead: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(item: tuple[str, Any]) -> bool:
        """Hands ``item`` over; False once the consumer has gone."""
        while not stop.is_set():
            try:
                ahead.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def decode() -> None:
        try:
            for frame in frames:
                if not put(("frame", frame)):
                    return
            put(("end", None))
        except BaseException as error:  # handed over to the consumer
            put(("error", error))

    thread = threading.Thread(target=decode, daemon=True)
    thread.start()
    try:
        while True:
            kind, value = ahead.get()
            if kind == "end":
                return
            if kind == "error":
                raise value
            yield value
    finally:
        stop.set()
