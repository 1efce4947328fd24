"""`track_corpus`: a corpus as one Ray Data job, resumable and fault tolerant.

The job: rows of videos (those not already done with the same settings) → `probe_video`
in CPU tasks → `VideoTracker` actors (one predictor each; one GPU each where the cluster
has GPUs) → one outcome row per video, counted by `Progress`. Ray restarts a dead actor
and retries its video; the tries are bounded per video by the attempt markers of
`taptr.corpus.results` (each actor runs one video at a time, so a death retries only the
video it killed), which turn the last allowed retry into a failure row. After
the job, every video still without a result or a failure record (the job itself failed)
is recorded as failed: no video is dropped silently.
"""

from __future__ import annotations

import builtins
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Any

from taptr.corpus.inputs import CorpusVideo, video_key
from taptr.corpus.probe import one_line, probe_video
from taptr.corpus.progress import Progress, Summary
from taptr.corpus.results import ResultLayout
from taptr.corpus.worker import TrackOptions, VideoTracker

if TYPE_CHECKING:
    from taptr.api.predictor import Predictor

INSTALL_HINT = 'tracking a corpus needs Ray: pip install "taptr[ray]"'
"""What to do when Ray (or pyarrow) is missing."""

PROBE_CPUS = 0.0
"""CPUs a header-reading task asks for: none, so that actors holding every CPU cannot starve
the tasks that feed them (a header takes milliseconds to read)."""

ACTORS_PER_PROBE = 8
"""Tracker actors one header-reading task keeps fed (a header takes milliseconds, a video
seconds); more tasks at once would only start more worker processes."""

MAX_BLOCKS = 2000
"""Most blocks the corpus rows are cut into (small corpora: one video per block)."""


@dataclass(frozen=True)
class CorpusOptions:
    """How a corpus is run.

    Attributes:
        out: output folder (on a cluster, one that every node mounts).
        actors: tracker actors; None: one per GPU of the cluster, else one per
            ``cpus_per_actor`` CPUs.
        cpus_per_actor: CPUs each actor reserves (torch threads on CPU actors).
        gpus_per_actor: GPUs each actor reserves; None: 1 where the cluster has GPUs, else 0.
        max_attempts: attempts at a video whose worker dies before it is recorded as failed.
        max_frames: track at most this many frames of each video.
        max_video_frames: refuse (record as failed) videos that declare more frames.
        backward: also track before each query frame.
        overwrite: track videos again even where a result with the same settings exists.
        retry_failed: track the videos recorded as failed with the same settings again
            (by default a rerun leaves them, as it leaves the finished ones).
        progress_every: seconds between progress lines.
        address: the Ray cluster to join (None: ``RAY_ADDRESS``, else a local instance).
    """

    out: str
    actors: int | None = None
    cpus_per_actor: float = 1.0
    gpus_per_actor: float | None = None
    max_attempts: int = 3
    max_frames: int | None = None
    max_video_frames: int | None = None
    backward: bool = False
    overwrite: bool = False
    retry_failed: bool = False
    progress_every: float = 30.0
    address: str | None = None


def require_ray() -> ModuleType:
    """Imports Ray (and checks pyarrow), or says how to install them."""
    try:
        import pyarrow  # noqa: F401
        import ray
        import ray.data
    except ModuleNotFoundError:
        raise ModuleNotFoundError(INSTALL_HINT) from None
    return ray


def track_corpus(
    videos: list[CorpusVideo],
    make_predictor: Callable[[], Predictor],
    options: CorpusOptions,
    print_line: Callable[..., Any] = print,
) -> Summary:
    """Tracks every video of a corpus not already done; returns what happened.

    Args:
        videos: the corpus, each with its settings digest (unique ids).
        make_predictor: builds a predictor; called once in each actor (it is pickled).
        options: see `CorpusOptions`.
        print_line: where progress lines go.

    Raises:
        ValueError: two videos with one id.
        ModuleNotFoundError: Ray is not installed (the message says how to install it).
    """
    ray = require_ray()
    _check_unique(videos)
    started = time.perf_counter()
    layout = ResultLayout(options.out)
    layout.prepare()
    rows = list({video.video_id: _row(video) for video in videos}.values())
    summary = Summary(total=len(rows))
    todo = _todo(rows, layout, options, summary)
    if todo:
        _join(ray, options.address)
        progress = Progress(summary, len(todo), options.progress_every, print_line)
        # Ray Data's progress bars replace builtins.print for the whole process and leave
        # it replaced; the caller's print is its own
        own_print = builtins.print
        try:
            for outcome in _dataset(ray, todo, make_predictor, options).iter_rows():
                progress.update(outcome)
        except Exception as error:  # Ray gave up: record what it left, then report it
            _record_lost(layout, todo, summary, f"the Ray job failed: {one_line(error)}")
        finally:
            builtins.print = own_print
        _record_lost(layout, todo, summary, "the Ray job ended without a result for it")
    layout.finish()
    summary.seconds = time.perf_counter() - started
    layout.write_summary(summary.as_dict())
    return summary


def _join(ray: ModuleType, address: str | None) -> None:
    """Joins the cluster ``address`` (None: ``RAY_ADDRESS`` or a new local instance).

    Raises:
        ValueError: the cluster cannot be reached or refuses the connection (one line).
    """
    if ray.is_initialized():
        return
    try:
        ray.init(address=address, log_to_driver=True)
    except (ConnectionError, ray.exceptions.RayError) as error:
        where = address or os.environ.get("RAY_ADDRESS") or "a local instance"
        raise ValueError(f"cannot join the Ray cluster ({where}): {one_line(error)}") from None


def actor_resources(ray: ModuleType, options: CorpusOptions) -> tuple[int, float, float]:
    """(actors, CPUs each, GPUs each) from the options and the cluster's resources."""
    resources = ray.cluster_resources()
    gpus = options.gpus_per_actor
    if gpus is None:
        gpus = 1.0 if resources.get("GPU", 0) >= 1 else 0.0
    actors = options.actors
    if actors is None:
        have = resources.get("GPU", 0) / gpus if gpus else resources.get("CPU", 1)
        actors = max(1, int(have // (1 if gpus else options.cpus_per_actor)))
    return actors, options.cpus_per_actor, gpus


def _dataset(
    ray: ModuleType,
    rows: list[dict[str, str]],
    make_predictor: Callable[[], Predictor],
    options: CorpusOptions,
) -> Any:
    """The Ray Data job: probe tasks, then tracker actors (one video per actor call)."""
    actors, cpus, gpus = actor_resources(ray, options)
    track = TrackOptions(options.out, options.max_attempts, options.max_frames, options.backward)
    forwarded = _forwarded_environment()
    # workers start faster without a runtime environment of their own
    environment = {"runtime_env": {"env_vars": forwarded}} if forwarded else {}
    return (
        ray.data.from_items(rows, override_num_blocks=min(len(rows), MAX_BLOCKS))
        .map(
            probe_video,
            fn_kwargs={"max_video_frames": options.max_video_frames},
            num_cpus=PROBE_CPUS,
            compute=ray.data.TaskPoolStrategy(size=max(1, actors // ACTORS_PER_PROBE)),
            **environment,
        )
        .map_batches(
            VideoTracker,
            fn_constructor_kwargs={
                "make_predictor": make_predictor,
                "options": track,
                "threads": None if gpus else max(1, int(cpus)),
            },
            batch_size=1,
            compute=ray.data.ActorPoolStrategy(size=actors, max_tasks_in_flight_per_actor=1),
            num_cpus=cpus,
            num_gpus=gpus,
            # Ray Data restarts dead actors and retries their tasks without limit; one
            # video in flight per actor, so a death retries only the video it killed, and
            # the attempt markers bound the tries of each video (then it is a failure row)
            **environment,
        )
    )


def _todo(
    rows: list[dict[str, str]], layout: ResultLayout, options: CorpusOptions, summary: Summary
) -> list[dict[str, str]]:
    """The rows to track now; counts the skipped ones (done, or failed before) in ``summary``."""
    done = set() if options.overwrite else layout.done()
    failed = set() if options.overwrite or options.retry_failed else layout.failed()
    todo = []
    for row in rows:
        name = f"{row['key']}.{row['digest']}.parquet"
        if name in done:
            summary.skipped += 1
        elif name in failed:
            summary.failed_before += 1
        else:
            todo.append(row)
    return todo


def _row(video: CorpusVideo) -> dict[str, str]:
    return {
        "video_id": video.video_id,
        "path": video.path,
        "queries": video.queries.to_json(),
        "digest": video.digest,
        "key": video_key(video.video_id),
    }


def _check_unique(videos: list[CorpusVideo]) -> None:
    seen: dict[str, str] = {}
    for video in videos:
        if seen.setdefault(video.video_id, video.path) != video.path:
            raise ValueError(
                f"the id {video.video_id!r} names two videos ({seen[video.video_id]} and "
                f"{video.path}); give each an id of its own"
            )


def _record_lost(
    layout: ResultLayout, rows: list[dict[str, str]], summary: Summary, reason: str
) -> None:
    """Records as failed every video of ``rows`` with neither a result nor a failure."""
    recorded = layout.done() | layout.failed()
    for row in rows:
        name = f"{row['key']}.{row['digest']}.parquet"
        if name in recorded:
            continue
        attempts = layout.attempts(row["key"], row["digest"])
        layout.write_failure(
            row["key"], row["video_id"], row["path"], reason, attempts, row["digest"]
        )
        summary.failed[row["video_id"]] = reason


def _forwarded_environment() -> dict[str, str]:
    """The driver's ``TAPTR_*`` variables (limits, the testing hook), for every worker."""
    return {name: value for name, value in os.environ.items() if name.startswith("TAPTR_")}
