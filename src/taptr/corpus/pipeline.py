"""`run_corpus`: a corpus on a Ray cluster, resumable, every video accounted for.

The run: check the output folder (`taptr.corpus.layout`) → leave out the videos its
index says are done (or failed) with the same settings → join the cluster and size the
actors before Ray could wait on them (`taptr.corpus.cluster`) → hand the rest to tracker
actors (`taptr.corpus.scheduler`, `taptr.corpus.worker`) → remove superseded rows
(`taptr.corpus.compaction`) → write the summary. Ctrl-C or SIGTERM stop handing out
videos, give the actors `STOP_GRACE_SECONDS` to write what they hold, write the summary
(``state: interrupted``) and end the job's Ray processes before the exception goes on;
any other error ends it as ``failed``, with the error.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np

from taptr.corpus.cluster import (
    PROCESS_BYTES,
    ActorShape,
    joined,
    plan_actors,
    require_ray,
)
from taptr.corpus.compaction import compact
from taptr.corpus.damage import sound_index
from taptr.corpus.inputs import CorpusVideo
from taptr.corpus.layout import ResultLayout, new_run
from taptr.corpus.parts import PartLimits, PartWriter
from taptr.corpus.progress import Progress, Summary
from taptr.corpus.records import Finished, VideoTask
from taptr.corpus.scheduler import JobError, Scheduler, SchedulerOptions
from taptr.corpus.signals import remembered_stop
from taptr.corpus.standing import standing
from taptr.corpus.worker import TrackerWorker, WorkerOptions
from taptr.messages import error_line, printable

if TYPE_CHECKING:
    import pyarrow as pa

    from taptr.api.spec import ModelSpec

STOP_GRACE_SECONDS = 20.0
"""After Ctrl-C or SIGTERM: how long actors may take to finish their calls and write."""

DEFAULT_ACTOR_MEMORY = PROCESS_BYTES + 512 * 2**20
"""Memory reserved per actor when the caller does not size it from its model."""


@dataclass(frozen=True)
class CorpusOptions:
    """How a corpus is run.

    Attributes:
        out: output folder or URI (on a cluster, one every node reaches).
        actors: tracker actors; None: as many as the cluster holds (one per GPU with
            GPUs, else one per ``cpus_per_actor`` CPUs, within memory).
        cpus_per_actor: CPUs each actor reserves (torch threads on CPU actors).
        gpus_per_actor: GPUs each actor reserves; None: 1 where the cluster has GPUs, else 0.
        memory_per_actor: bytes each actor reserves; None: estimated from the model by
            `taptr.corpus.track_corpus` (`run_corpus` alone reserves `DEFAULT_ACTOR_MEMORY`).
        max_attempts: deaths of its actor while tracking a video before it is failed.
        max_frames: track at most this many frames of each video.
        max_video_frames: refuse (record as failed) videos that declare more frames.
        backward: also track before each query frame.
        accept_truncated: keep the tracks of videos that decode to fewer frames than
            their containers declare (by default they are failures).
        overwrite: track videos again even where a result with the same settings exists.
        retry_failed: track the videos recorded as failed with the same settings again.
        progress_every: seconds between progress lines.
        address: the Ray cluster to join (None: ``RAY_ADDRESS``, else a local instance).
        parts: when actors write their parts.
        start_timeout: seconds an actor may take to start before it is dropped.
    """

    out: str
    actors: int | None = None
    cpus_per_actor: float = 1.0
    gpus_per_actor: float | None = None
    memory_per_actor: int | None = None
    max_attempts: int = 3
    max_frames: int | None = None
    max_video_frames: int | None = None
    backward: bool = False
    accept_truncated: bool = False
    overwrite: bool = False
    retry_failed: bool = False
    progress_every: float = 30.0
    address: str | None = None
    parts: PartLimits = field(default_factory=PartLimits)
    start_timeout: float = 300.0


def run_corpus(
    videos: list[CorpusVideo],
    model: ModelSpec,
    options: CorpusOptions,
    print_line: Callable[..., Any] = print,
    worker: type[TrackerWorker] = TrackerWorker,
) -> Summary:
    """Tracks every video of a corpus not already done; returns what happened.

    `taptr.corpus.track_corpus` is the entry point: it gives each video its settings
    digest and sizes the actors' memory, then calls this.

    Args:
        videos: the corpus, each with its settings digest (`taptr.corpus.settings`) and
            a unique id.
        model: the tracker each actor loads once (`ModelSpec.load`; it is pickled).
        options: see `CorpusOptions`.
        print_line: where progress lines go.
        worker: the actor class (benchmarks put a named stand-in here).

    Raises:
        ValueError: ids given twice, a folder holding foreign files, an impossible
            request of the cluster, a store that does not answer, or a job that cannot
            go on (one line each).
        ModuleNotFoundError: Ray is not installed (the message says how to install it).
        KeyboardInterrupt: Ctrl-C or SIGTERM (what the process's handler raised), after
            the summary is written.
    """
    ray = require_ray()
    check_unique(videos)
    started = time.perf_counter()
    layout = ResultLayout.at(options.out)
    layout.check()  # before anything else: a foreign folder is refused at once
    summary = Summary(total=len(videos), run=new_run())
    index = sound_index(layout, print_line)
    todo = plan(videos, index, options, summary)
    # nothing to track: no cluster to join (a finished corpus reruns in seconds)
    cluster = joined(ray, options.address) if todo else contextlib.nullcontext()
    with remembered_stop(), cluster:
        actors, shape = _size(ray, options) if todo else (0, None)
        layout.prepare()
        layout.write_summary(summary.as_dict())  # "running": an old summary is not this run's
        try:
            compact(layout, summary.run, index, print_line)  # what a stopped run superseded
            if todo and shape is not None:
                starter = _actor_starter(ray, worker, model, options, summary.run, shape)
                _run(todo, starter, options, (layout, summary, actors), print_line)
                compact(layout, summary.run, print_line=print_line)  # what this run did
            layout.finish()
            summary.state = "finished"
        except BaseException as error:  # whatever stopped it, the summary says so
            if summary.state == "running":
                _stopped(summary, error)
            raise
        finally:
            summary.seconds = time.perf_counter() - started
            layout.write_summary(summary.as_dict())
            if summary.state != "finished":  # the caller gets an exception, not the summary
                print_line(summary.line(), flush=True)
    return summary


def _stopped(summary: Summary, error: BaseException) -> None:
    """Records in the summary why a run stopped (an interrupt, or an error)."""
    if isinstance(error, KeyboardInterrupt):
        summary.state = "interrupted"
    else:
        summary.state, summary.error = "failed", error_line(error)


def plan(
    videos: list[CorpusVideo], index: pa.Table, options: CorpusOptions, summary: Summary
) -> list[VideoTask]:
    """The videos to track now; counts the skipped ones (done, or failed before).

    A video is done when its standing result in ``index`` (`taptr.corpus.standing`) has
    its digest, failed before when its standing failure has it. Each video finds its
    standing row by Arrow's ``index_in``: a rerun over 10⁶ done videos builds no Python
    object per video.
    """
    done, failed_before = _skipped(videos, index, options)
    summary.skipped += int(done.sum())
    summary.failed_before += int(failed_before.sum())
    tasks: list[VideoTask] = []
    spec_text: dict[int, str] = {}  # videos share their QuerySpec objects: one JSON each
    for position in np.flatnonzero(~(done | failed_before)):
        video = videos[position]
        text = spec_text.get(id(video.queries))
        if text is None:
            text = spec_text[id(video.queries)] = video.queries.to_json()
        tasks.append(VideoTask(len(tasks), video.video_id, video.path, text, video.digest))
    return tasks


def _skipped(
    videos: list[CorpusVideo], index: pa.Table, options: CorpusOptions
) -> tuple[np.ndarray, np.ndarray]:
    """(done, failed before) as (len(videos),) bool masks."""
    import pyarrow as pa
    import pyarrow.compute as pc

    nothing = np.zeros(len(videos), bool)
    if options.overwrite or len(index) == 0:
        return nothing, nothing
    found = standing(index)
    ids = pa.array([video.video_id for video in videos], pa.string())
    # (V,) each video's row of `found`, null for a video the index does not hold
    rows = pc.index_in(ids, value_set=found["video_id"].combine_chunks())
    digests = pa.array([video.digest for video in videos], pa.string())

    def same(column: str) -> np.ndarray:
        equal = pc.equal(digests, found[column].take(rows))
        return pc.fill_null(equal, False).to_numpy(zero_copy_only=False)

    done = same("done_digest")
    if options.retry_failed:
        return done, nothing
    return done, same("failed_digest") & ~done


def check_unique(videos: list[CorpusVideo]) -> None:
    """Refuses a corpus that gives one id to two videos (or to one video twice).

    Raises:
        ValueError: names the id and both positions.
    """
    first: dict[str, int] = {}
    for number, video in enumerate(videos, 1):
        earlier = first.setdefault(video.video_id, number)
        if earlier != number:
            raise ValueError(
                f"the id {printable(video.video_id)!r} is given to videos {earlier} and "
                f"{number} of the corpus ({videos[earlier - 1].path} and {video.path}); give "
                "each video an id of its own"
            )


def _size(ray: ModuleType, options: CorpusOptions) -> tuple[int, ActorShape]:
    """(actors, what each reserves), checked against the cluster."""
    gpus = options.gpus_per_actor
    if gpus is None:
        gpus = 1.0 if ray.cluster_resources().get("GPU", 0) >= 1 else 0.0
    memory = options.memory_per_actor or DEFAULT_ACTOR_MEMORY
    shape = ActorShape(options.cpus_per_actor, gpus, memory)
    return plan_actors(ray, options.actors, shape), shape


def _run(
    tasks: list[VideoTask],
    start_actor: Callable[[], Any],
    options: CorpusOptions,
    context: tuple[ResultLayout, Summary, int],
    print_line: Callable[..., Any],
) -> None:
    """Runs the scheduler to the end (or to a stop); counts into the summary."""
    layout, summary, actors = context
    progress = Progress(summary, len(tasks), options.progress_every, print_line)

    def on_commit(finished: Finished, attempts: int) -> None:
        summary.commit(finished, attempts, tasks[finished.index].video_id)
        progress.update(finished)  # counted once written, as the summary counts it

    scheduler = Scheduler(
        tasks,
        start_actor,
        layout,
        PartWriter(layout, summary.run, options.parts),
        SchedulerOptions(actors, options.max_attempts, options.start_timeout),
        on_commit,
    )
    try:
        _drive(scheduler, progress)
    except KeyboardInterrupt:  # Ray's own for a signal inside its wait: see `signals`
        summary.state = "interrupted"
        _stop(scheduler, progress)
        raise
    except JobError as error:
        summary.state, summary.error = "failed", error_line(error)
        raise ValueError(summary.error) from None
    finally:
        summary.left = len(scheduler.close())
        if scheduler.first_ready is not None:
            summary.tracking_seconds = time.monotonic() - scheduler.first_ready
        progress.final()


def _drive(scheduler: Scheduler, progress: Progress) -> None:
    while scheduler.step():
        if scheduler.first_ready is not None:
            progress.start(scheduler.first_ready)
        progress.tick()


def _stop(scheduler: Scheduler, progress: Progress) -> None:
    """Lets the actors finish their calls and write, for at most `STOP_GRACE_SECONDS`."""
    scheduler.stop()
    deadline = time.monotonic() + STOP_GRACE_SECONDS
    try:
        while time.monotonic() < deadline and scheduler.step():
            progress.tick()
    except KeyboardInterrupt:  # a second signal: stop now
        pass


def _actor_starter(
    ray: ModuleType,
    worker: type[TrackerWorker],
    model: ModelSpec,
    options: CorpusOptions,
    run: str,
    shape: ActorShape,
) -> Callable[[], Any]:
    from taptr.corpus.storage import Storage

    settings = WorkerOptions(
        storage=Storage(options.out),
        run=run,
        parts=options.parts,
        max_frames=options.max_frames,
        max_video_frames=options.max_video_frames,
        backward=options.backward,
        accept_truncated=options.accept_truncated,
    )
    threads = None if shape.gpus else max(1, int(shape.cpus))
    forwarded = _forwarded_environment()
    actor = ray.remote(worker).options(
        num_cpus=shape.cpus,
        num_gpus=shape.gpus,
        memory=shape.memory,
        max_restarts=0,  # the driver replaces dead actors: it knows what each was doing
        max_task_retries=0,
        max_concurrency=2,  # `stop` arrives while `run` works
        # workers start faster without a runtime environment of their own
        **({"runtime_env": {"env_vars": forwarded}} if forwarded else {}),
    )

    def start() -> Any:
        return actor.remote(model, settings, threads)

    return start


def _forwarded_environment() -> dict[str, str]:
    """The driver's ``TAPTR_*`` variables (limits, the testing hook), for every actor."""
    import os

    return {name: value for name, value in os.environ.items() if name.startswith("TAPTR_")}
