"""``taptr track-corpus``: track a corpus of videos as a Ray Data job (docs/CORPUS.md)."""

from __future__ import annotations

import argparse
import copy
import functools
import hashlib
import json
from typing import TYPE_CHECKING

from taptr.cli.model_options import add_model_arguments, check_model_arguments, load_predictor
from taptr.cli.options import check_at_least, check_output_folder
from taptr.cli.points import add_query_arguments, listed_points

if TYPE_CHECKING:
    from taptr.api.predictor import Predictor
    from taptr.corpus.inputs import CorpusVideo, QuerySpec

MAX_LISTED_FAILURES = 20
"""Failed videos named in the closing lines (all of them are in OUT/failures/)."""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    parser = subparsers.add_parser(
        "track-corpus",
        help="track a corpus of videos on a Ray cluster or a local Ray instance",
        description="Tracks every video of a corpus as a Ray Data job: CPU tasks read and "
        "check each video's header, actors holding one model each (one GPU each where the "
        "cluster has GPUs) stream its frames through the tracker. Results go to "
        "OUT/tracks/ as a Parquet dataset (one row per video and point; schema in "
        "docs/CORPUS.md), a video's rows appearing all at once; videos that cannot be "
        "tracked are recorded in OUT/failures/ with their error while the rest go on. A "
        "rerun skips the videos whose results were made with the same settings, and those "
        "recorded as failed with them (see --retry-failed). Without "
        "RAY_ADDRESS or --address, a local Ray instance is started. Needs the extra: "
        'pip install "taptr[ray]".',
    )
    parser.add_argument(
        "inputs",
        nargs="+",
        help="video files, folders of videos, quoted glob patterns, or manifests (.csv or "
        ".parquet with a 'path' column and optional 'id', 'points', 'grid', 'mask', "
        "'query_frame' columns)",
    )
    add_query_arguments(parser, required=False)
    parser.add_argument(
        "--backward", action="store_true", help="also track before each query frame"
    )
    parser.add_argument(
        "--out", default="corpus-results", help="output folder (default: corpus-results)"
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
        "--actors",
        type=int,
        default=None,
        help="tracker actors (default: one per GPU of the cluster, else one per "
        "--cpus-per-actor CPUs)",
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
        "--attempts",
        type=int,
        default=3,
        help="attempts at a video whose actor dies (killed, out of memory) before it is "
        "recorded as failed (default: 3)",
    )
    parser.add_argument(
        "--max-video-frames",
        type=int,
        default=None,
        metavar="N",
        help="record videos that declare more than N frames as failed instead of tracking them",
    )
    parser.add_argument(
        "--progress-every",
        type=float,
        default=30.0,
        metavar="SECONDS",
        help="seconds between progress lines (default: 30)",
    )
    parser.add_argument(
        "--address",
        default=None,
        help="Ray cluster to join, e.g. auto or ray://HEAD:10001 (default: RAY_ADDRESS, "
        "else a local instance)",
    )
    add_model_arguments(parser)
    parser.set_defaults(func=run, trajectories=False)


def run(args: argparse.Namespace) -> int:
    """Tracks the corpus; prints progress lines and a summary; 2 if a video has failed."""
    from taptr.corpus.pipeline import CorpusOptions, require_ray, track_corpus

    _check_arguments(args)
    require_ray()  # before the model loads: say at once how to install it
    videos = corpus_videos(args)
    predictor = load_predictor(_on_cpu(args))  # the settings, as the actors will have them
    videos = with_digests(videos, args, predictor)
    del predictor
    options = CorpusOptions(
        out=args.out,
        actors=args.actors,
        cpus_per_actor=args.cpus_per_actor,
        gpus_per_actor=args.gpus_per_actor,
        max_attempts=args.attempts,
        max_frames=args.max_frames,
        max_video_frames=args.max_video_frames,
        backward=args.backward,
        overwrite=args.overwrite,
        retry_failed=args.retry_failed,
        progress_every=args.progress_every,
        address=args.address,
    )
    summary = track_corpus(videos, functools.partial(load_predictor, args), options)
    print(summary.line() + f"; results in {args.out}/tracks/", flush=True)
    for video_id, error in list(summary.failed.items())[:MAX_LISTED_FAILURES]:
        print(f"  failed: {video_id}: {error}")
    if len(summary.failed) > MAX_LISTED_FAILURES:
        print(f"  ... and {len(summary.failed) - MAX_LISTED_FAILURES} more in {args.out}/failures/")
    if summary.failed_before:
        print(
            f"  {summary.failed_before} failed in earlier runs ({args.out}/failures/); "
            "--retry-failed tracks them again"
        )
    return 2 if summary.failed or summary.failed_before else 0


def _check_arguments(args: argparse.Namespace) -> None:
    check_output_folder(args.out)
    check_model_arguments(args)
    check_at_least(args.query_frame, 0, "--query-frame")
    check_at_least(args.mask_stride, 1, "--mask-stride")
    check_at_least(args.attempts, 1, "--attempts")
    if args.actors is not None:
        check_at_least(args.actors, 1, "--actors")
    if args.max_video_frames is not None:
        check_at_least(args.max_video_frames, 1, "--max-video-frames")
    if not args.cpus_per_actor > 0:
        raise ValueError(f"--cpus-per-actor must be above 0, got {args.cpus_per_actor}")
    if args.gpus_per_actor is not None and not args.gpus_per_actor >= 0:
        raise ValueError(f"--gpus-per-actor must be 0 or more, got {args.gpus_per_actor}")


def corpus_videos(args: argparse.Namespace) -> list[CorpusVideo]:
    """The videos the inputs name, manifests read, with the options' queries as defaults."""
    from taptr.cli.videos import expand_videos
    from taptr.corpus.inputs import CorpusVideo
    from taptr.corpus.manifest import is_manifest, read_manifest

    default = default_queries(args)
    videos: list[CorpusVideo] = []
    for item in args.inputs:
        if is_manifest(item):
            videos += read_manifest(item, default)
            continue
        if default is None:
            raise ValueError(
                f"{item}: give the queries with --points, --points-file, --grid or --mask "
                "(or list the videos in a manifest with their own)"
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


def with_digests(
    videos: list[CorpusVideo], args: argparse.Namespace, predictor: Predictor
) -> list[CorpusVideo]:
    """The videos with their settings digests (16 hex digits).

    A digest hashes `track_settings` (the record ``taptr track`` keeps in settings.json)
    with the video's own queries.
    """
    from dataclasses import replace

    import numpy as np

    from taptr.cli.result_settings import query_settings, track_settings

    base = track_settings(args, predictor, None)
    digests: dict[QuerySpec, str] = {}  # corpora share a few query specs among many videos
    for spec in dict.fromkeys(video.queries for video in videos):
        options = copy.copy(args)
        vars(options).update(
            points=None, grid=spec.grid, mask=spec.mask, query_frame=spec.query_frame
        )
        listed = None if spec.points is None else np.asarray(spec.points, np.float32)
        settings = {**base, "queries": query_settings(options, listed)}
        text = json.dumps(settings, sort_keys=True)
        digests[spec] = hashlib.sha256(text.encode()).hexdigest()[:16]
    return [replace(video, digest=digests[video.queries]) for video in videos]


def _on_cpu(args: argparse.Namespace) -> argparse.Namespace:
    """The options with the model on the CPU, uncompiled (the driver only reads settings)."""
    cpu = copy.copy(args)
    cpu.device, cpu.compile, cpu.frames_per_call, cpu.kernel = "cpu", False, 1, "gather"
    return cpu
