"""The tracker actor of a corpus: one `Predictor`, many videos, results written in parts.

The driver (`taptr.corpus.scheduler`) calls `TrackerWorker.run` with a list of videos;
it is a Ray streaming generator whose items are lists of events
(`taptr.corpus.records`). For each video the actor reads the header and builds the
queries (`taptr.corpus.probe`); a video that passes is announced with `Started` before
its frames are decoded, so that a death of the actor is charged to that video alone.
Frames stream from the decoder through `taptr.api.streaming.track_frames` (a reader
thread decodes a few frames ahead while the model runs), so an actor's memory stays flat
in the video's length; only the tracks (T × N) are held until the part is written
(`taptr.corpus.parts`).

Testing hook: ``TAPTR_CORPUS_KILL="VIDEO_ID:N[,VIDEO_ID:N...]"`` makes an actor exit
abruptly (``os._exit``, as the OOM killer would end it) in the middle of that video's first
N tracking attempts.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from taptr.corpus.layout import ResultLayout
from taptr.corpus.parts import PartLimits, PartWriter
from taptr.corpus.probe import Probed, ProbeError, probe_video
from taptr.corpus.records import (
    DONE,
    FAILED,
    Event,
    Failure,
    Finished,
    Started,
    VideoTask,
    VideoTracks,
)
from taptr.corpus.storage import Storage
from taptr.io.frame_count import TruncatedVideoError, check_decoded
from taptr.messages import error_line

if TYPE_CHECKING:
    from taptr.api.predictor import Predictor
    from taptr.api.spec import ModelSpec

KILL_VARIABLE = "TAPTR_CORPUS_KILL"
"""The fault-injection hook's environment variable (tests only)."""

READ_AHEAD = 8
"""Frames the reader thread decodes ahead of the tracker."""


@dataclass(frozen=True)
class WorkerOptions:
    """How each video is tracked and recorded.

    Attributes:
        storage: the output folder.
        run: the run's id (in every part's name).
        parts: when a part is written.
        max_frames: track at most this many frames of each video (None: all).
        max_video_frames: refuse videos that declare more frames (None: no limit).
        backward: also track before each query frame (the file is read twice).
        accept_truncated: keep the tracks of a video that decodes to fewer frames than
            its container declares (by default it is a failure).
    """

    storage: Storage
    run: str
    parts: PartLimits = field(default_factory=PartLimits)
    max_frames: int | None = None
    max_video_frames: int | None = None
    backward: bool = False
    accept_truncated: bool = False


class TrackerWorker:
    """A Ray actor holding one predictor and the part it is filling.

    Args:
        model: the tracker, built once in the actor (`ModelSpec.load`).
        options: how to track and where to write.
        threads: CPU threads of a CPU actor, its reserved CPUs, unless the spec names its own
            (None: as the spec says, `taptr.runtime.threads.choose_threads`).
    """

    def __init__(
        self,
        model: ModelSpec,
        options: WorkerOptions,
        threads: int | None = None,
    ) -> None:
        if threads is not None and model.threads is None:
            model = replace(model, threads=threads)
        # the driver has told the user which model runs: once per run, not per actor
        logging.getLogger("taptr").setLevel(logging.ERROR)
        self.predictor = self.load(model)
        self.options = options
        self.parts = PartWriter(ResultLayout(options.storage), options.run, options.parts)
        self.stopping = False  # set by `stop` from the actor's second thread

    def load(self, model: ModelSpec) -> Predictor:
        """The actor's predictor (benchmarks' stand-in loads none).

        A graph engine's `taptr.api.graph_predictor.GraphPredictor` has the surface used here.
        """
        return model.load()  # type: ignore[return-value]

    def ready(self) -> str:
        """The actor's writer id (names its parts), once its model is loaded."""
        return self.parts.writer

    def run(self, tasks: list[VideoTask]) -> Iterator[list[Event]]:
        """Tracks ``tasks`` in order, yielding events (see the module docstring)."""
        events: list[Event] = []
        for task in tasks:
            if self.stopping:  # the rest of the batch goes back to the driver untouched
                break
            started = time.perf_counter()
            try:
                probed = self._probe(task)
            except Exception as error:  # every reason a video cannot be read is a failure
                declared = error.declared_frames if isinstance(error, ProbeError) else None
                failure = Failure(
                    task.video_id, task.path, error_line(error), 0, declared, None, task.digest
                )
                events.append(self._failed(task.index, failure, started))
            else:
                yield events + [Started(task.index)]
                events = [self._track_one(task, probed, started)]
            if self.parts.due():
                events.append(self.parts.flush())  # type: ignore[arg-type]
        if events:
            yield events

    def stop(self) -> None:
        """Ends the current call after the video in progress (the job is stopping)."""
        self.stopping = True

    def flush(self) -> Iterator[list[Event]]:
        """Writes the waiting videos as a part now (the driver's call when idle or done).

        A generator of one item, like `run`, so the driver reads both alike.
        """
        committed = self.parts.flush()
        yield [] if committed is None else [committed]

    def _probe(self, task: VideoTask) -> Probed:
        """The video's header and queries (`taptr.corpus.probe.probe_video`)."""
        return probe_video(task, self.options.max_video_frames)

    def _track_one(self, task: VideoTask, probed: Probed, started: float) -> Finished:
        """Tracks one video into the part, or records why it failed."""
        try:
            video = self._track(task, probed)
        except Exception as error:  # a bad video must not stop the others
            decoded = error.decoded if isinstance(error, TruncatedVideoError) else None
            failure = Failure(
                task.video_id,
                task.path,
                error_line(error),
                task.attempt,
                probed.info.num_frames,
                decoded,
                task.digest,
            )
            return self._failed(task.index, failure, started)
        self.parts.add_tracks(task.index, video)
        frames, points = video.visibility.shape
        seconds = time.perf_counter() - started
        return Finished(task.index, DONE, "", frames, points, seconds)

    def _failed(self, index: int, failure: Failure, started: float) -> Finished:
        self.parts.add_failure(index, failure)
        return Finished(index, FAILED, failure.error, seconds=time.perf_counter() - started)

    def _track(self, task: VideoTask, probed: Probed) -> VideoTracks:
        from taptr.api.online import FrameCountError

        info, options = probed.info, self.options
        declared = info.num_frames
        expected = (
            declared if options.max_frames is None else min(declared or 0, options.max_frames)
        )
        tracks = visibility = None
        if expected:
            try:
                tracks, visibility = self._stream(task, probed.queries, expected)
            except FrameCountError as error:  # the container's frame count was wrong
                if error.short:
                    check_decoded(
                        task.path,
                        error.seen,
                        declared,
                        options.max_frames,
                        options.accept_truncated,
                    )
        if tracks is None or visibility is None:
            tracks, visibility = self._in_memory(task.path, probed.queries)
            check_decoded(
                task.path, len(tracks), declared, options.max_frames, options.accept_truncated
            )
        return VideoTracks(
            video_id=task.video_id,
            path=task.path,
            queries=probed.queries,
            tracks=tracks,
            visibility=visibility,
            size=(info.height, info.width),
            fps=info.fps,
            declared_frames=declared,
            model=str(self.predictor.source),
            digest=task.digest,
        )

    def _stream(
        self, task: VideoTask, queries: np.ndarray, num_frames: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Tracks frame by frame: (T, N, 2) tracks and (T, N) visibility."""
        from taptr.api.streaming import track_frames, track_frames_both_ways
        from taptr.io.reverse_frames import iter_frames_reversed
        from taptr.io.video import iter_frames

        path, limit = task.path, self.options.max_frames
        doomed = _doomed(task.video_id, task.attempt)

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
        """For containers that do not state their length (or state a wrong one)."""
        from taptr.io.video import read_video

        frames = read_video(path, max_frames=self.options.max_frames)
        result = self.predictor.track(frames, queries, backward=self.options.backward)
        return result.tracks[0].numpy(), result.visibility[0].numpy()


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
