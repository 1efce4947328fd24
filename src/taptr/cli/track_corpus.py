"""``taptr track-corpus``: track a corpus of videos on a Ray cluster (docs/CORPUS.md)."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from taptr.cli.common.model_options import (
    add_model_arguments,
    check_model_arguments,
    model_spec,
)
from taptr.cli.common.options import check_at_least, check_output_folder
from taptr.cli.common.points import add_query_arguments, listed_points
from taptr.io.frame_count import ACCEPT_TRUNCATED

if TYPE_CHECKING:
    from taptr.corpus.inputs import CorpusVideo, QuerySpec
    from taptr.corpus.pipeline import CorpusOptions

DESCRIPTION = (
    "Tracks every video of a corpus on a Ray cluster (or a local Ray instance): tracker "
    "actors, one model each (one GPU each where the cluster has GPUs), read each video's "
    "header, stream its frames through the tracker and write the rows of many videos at "
    "once as a part of OUT/tracks/, a Parquet dataset (one row per video and point; schema "
    "in docs/CORPUS.md). A video counts as done once its part is written and read back; "
    "videos that cannot be tracked are recorded in OUT/failures/ with their error while "
    "the rest go on. A rerun skips the videos done with the same settings, and those "
    "recorded as failed with them (see --retry-failed). OUT may be a local folder or a URI "
    "that pyarrow opens (s3://bucket/prefix, gs://...). Without RAY_ADDRESS or --address, "
    'a local Ray instance is started. Needs the extra: pip install -e ".[ray]".'
)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    parser = subparsers.add_parser(
        "track-corpus",
        help="track a corpus of videos on a Ray cluster or a local Ray instance",
        description=DESCRIPTION,
    )
    parser.add_argument(
        "inputs",
        nargs="+",
        help="video files, folders of videos, quoted glob patterns, or video lists (.csv or "
        ".parquet with a 'path' column and optional 'id', 'points', 'grid', 'mask', "
        "'query_frame' columns)",
    )
    add_query_arguments(parser, required=False)
    _add_result_arguments(parser)
    _add_cluster_arguments(parser)
    add_model_arguments(parser, engines=True)
    parser.set_defaults(func=run, trajectories=False)


def _add_result_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--backward", action="store_true", help="also track before each query frame"
    )
    parser.add_argument(
        "--out",
        default="corpus-results",
        help="output folder or URI (s3://bucket/prefix; default: corpus-results)",
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="track videos already done with these settings"
    )
    parser.add_argument(
        "--retry-failed",
        action="store_true",
        help="track the videos recorded as failed with these settings again (a rerun "
        "leaves them by default)",
    )
    parser.add_argument(
        ACCEPT_TRUNCATED,
        action="store_true",
        help="keep the tracks of a video that decodes to fewer frames than its container "
        "declares (by default it is recorded as failed, with both counts)",
    )
    parser.add_argument(
        "--max-video-frames",
        type=int,
        default=None,
        metavar="N",
        help="record videos that declare more than N frames as failed instead of tracking them",
    )
    parser.add_argument(
        "--part-videos",
        type=int,
        default=1000,
        metavar="N",
        help="videos in one part of the dataset at most (default: 1000; parts are also "
        "written every --part-seconds and at 128 MiB)",
    )
    parser.add_argument(
        "--part-seconds",
        type=float,
        default=120.0,
        metavar="SECONDS",
        help="an actor writes its part at least this often, which bounds the work a dead "
        "actor loses (default: 120)",
    )
    parser.add_argument(
        "--migrate",
        action="store_true",
        help="first move results of taptr 0.1's layout (one file per video) in OUT into "
        "parts (docs/CORPUS.md)",
    )
    parser.add_argument(
        "--progress-every",
        type=float,
        default=30.0,
        metavar="SECONDS",
        help="seconds between progress lines (default: 30)",
    )


def _add_cluster_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--actors",
        type=int,
        default=None,
        help="tracker actors (default: as many as the cluster holds: one per GPU, else "
        "one per --cpus-per-actor CPUs, within memory)",
    )
    parser.add_argument(
        "--cpus-per-actor",
        type=float,
        default=1.0,
        help="CPUs each actor reserves; CPU actors use as many torch threads (default: 1)",
    )
    parser.add_argument(
        "--gpus-per-actor",
        type=float,
        default=None,
        help="GPUs each actor reserves, e.g. 0.5 for two actors a GPU (default: 1 where the "
        "cluster has GPUs, else 0)",
    )
    parser.add_argument(
        "--memory-per-actor",
        type=float,
        default=None,
        metavar="GIB",
        help="memory each actor reserves (default: estimated from the model for a 10 s "
        "720p clip with 256 points)",
    )
    parser.add_argument(
        "--attempts",
        type=int,
        default=3,
        help="deaths of its actor while tracking a video (killed, out of memory, node "
        "lost) before the video is recorded as failed (default: 3)",
    )
    parser.add_argument(
        "--actor-start-timeout",
        type=float,
        default=300.0,
        metavar="SECONDS",
        help="drop an actor that cannot start within this time, e.g. when its node is lost "
        "and the cluster cannot hold another (default: 300)",
    )
    parser.add_argument(
        "--address",
        default=None,
        help="Ray cluster to join, e.g. auto, HEAD:6379 or ray://HEAD:10001 (default: "
        "RAY_ADDRESS, else a local instance)",
    )


def run(args: argparse.Namespace) -> int:
    """Tracks the corpus (`taptr.corpus.track_corpus`); prints progress lines and a summary.

    Returns 2 when a video has failed, now or in an earlier run with these settings.
    """
    from taptr.corpus.cluster import check_address, require_ray
    from taptr.corpus.job import track_corpus
    from taptr.corpus.layout import ResultLayout
    from taptr.corpus.migrate import migrate

    _check_arguments(args)
    require_ray()  # before the video lists are read: say at once how to install it
    check_address(args.address)  # and that the cluster cannot be reached
    videos = corpus_videos(args)
    layout = ResultLayout.at(args.out)
    if args.migrate:
        print(f"moved {migrate(layout)} videos of the old layout into parts", flush=True)
    summary = track_corpus(videos, model_spec(args), _options(args))
    print(summary.line() + f"; results in {layout.tracks}", flush=True)
    for line in summary.failure_lines(layout.failures):
        print(line)
    if summary.failed_before:
        print(
            f"  {summary.failed_before} failed in earlier runs ({layout.failures}); "
            "--retry-failed tracks them again"
        )
    return 2 if summary.failed or summary.failed_before else 0


def _options(args: argparse.Namespace) -> CorpusOptions:
    from taptr.corpus.parts import PartLimits
    from taptr.corpus.pipeline import CorpusOptions

    return CorpusOptions(
        out=args.out,
        actors=args.actors,
        cpus_per_actor=args.cpus_per_actor,
        gpus_per_actor=args.gpus_per_actor,
        memory_per_actor=_gib(args.memory_per_actor),
        max_attempts=args.attempts,
        max_frames=args.max_frames,
        max_video_frames=args.max_video_frames,
        backward=args.backward,
        accept_truncated=args.accept_truncated,
        overwrite=args.overwrite,
        retry_failed=args.retry_failed,
        progress_every=args.progress_every,
        address=args.address,
        parts=PartLimits(videos=args.part_videos, seconds=args.part_seconds),
        start_timeout=args.actor_start_timeout,
    )


def _check_arguments(args: argparse.Namespace) -> None:
    from taptr.corpus.storage import check_scheme, uri_scheme

    check_scheme(args.out)
    if uri_scheme(args.out) is None:
        check_output_folder(args.out)
    check_model_arguments(args)
    check_at_least(args.query_frame, 0, "--query-frame")
    check_at_least(args.mask_stride, 1, "--mask-stride")
    check_at_least(args.attempts, 1, "--attempts")
    check_at_least(args.part_videos, 1, "--part-videos")
    if args.actors is not None:
        check_at_least(args.actors, 1, "--actors")
    if args.max_video_frames is not None:
        check_at_least(args.max_video_frames, 1, "--max-video-frames")
    for flag, value in (
        ("--cpus-per-actor", args.cpus_per_actor),
        ("--part-seconds", args.part_seconds),
        ("--actor-start-timeout", args.actor_start_timeout),
        ("--memory-per-actor", args.memory_per_actor),
    ):
        if value is not None and not value > 0:
            raise ValueError(f"{flag} must be above 0, got {value}")
    if args.gpus_per_actor is not None and not args.gpus_per_actor >= 0:
        raise ValueError(f"--gpus-per-actor must be 0 or more, got {args.gpus_per_actor}")


def corpus_videos(args: argparse.Namespace) -> list[CorpusVideo]:
    """The videos the inputs name, video lists read, with the options' queries as defaults.

    Raises:
        ValueError: no videos at all, or an input without queries.
    """
    from taptr.cli.common.videos import expand_videos
    from taptr.corpus.inputs import CorpusVideo
    from taptr.corpus.video_list import is_video_list, read_video_list

    default = default_queries(args)
    videos: list[CorpusVideo] = []
    for item in args.inputs:
        if is_video_list(item):
            videos += read_video_list(item, default)
            continue
        if default is None:
            raise ValueError(
                f"{item}: give the queries with --points, --points-file, --grid or --mask "
                "(or list the videos in a video list with their own)"
            )
        videos += [CorpusVideo(str(path), str(path), default) for path in expand_videos([item])]
    return videos


def default_queries(args: argparse.Namespace) -> QuerySpec | None:
    """The queries of the options (None when no query option is given)."""
    from taptr.corpus.inputs import QuerySpec, points_tuple

    listed = listed_points(args)
    if listed is None and args.grid is None and args.mask is None:
        return None
    return QuerySpec(
        points=None if listed is None else points_tuple(listed),
        grid=args.grid,
        mask=args.mask,
        query_frame=args.query_frame,
        mask_stride=args.mask_stride,
    )


def _gib(value: float | None) -> int | None:
    return None if value is None else int(value * 2**30)
