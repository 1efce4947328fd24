"""``taptr eval``: TAP-Vid evaluation of taptr or a baseline, with a per-video report.

Run it under ``torchrun --nproc_per_node K -m taptr.cli.main eval ...`` to share the videos
among K processes (gloo on CPU, NCCL on GPU); the result is the same as with one process.
"""

from __future__ import annotations

import argparse
import pickle

from taptr.cli.common.model_options import CHECKPOINT_HELP, SUPPORT_CHOICES
from taptr.cli.common.options import (
    add_device_argument,
    check_at_least,
    check_device,
    check_input_path,
    check_output_folder,
)

DESCRIPTION = """\
Scores a tracker on a TAP-Vid set (or Kubric-layout sequences) with the TAP-Vid metrics:
average Jaccard (AJ), average position accuracy (<δavg) and occlusion accuracy (OA).
Writes OUT/results.json (config, versions, git commit, per-video metrics and the mean, as
fractions) and OUT/videos.csv, and prints the per-video table (in percent).

protocols:
  standard  canonical TAP-Vid: 256x256 frames, raster coordinates, any tracker
  official  TAPTR's own evaluation (x255 coordinates, 512x512 model input, queries padded
            to 800): reproduces the paper's numbers with the released checkpoint
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    from taptr.eval.datasets import DATASETS
    from taptr.eval.metrics import QUERY_MODES
    from taptr.eval.runner import PROTOCOLS, TRACKERS

    parser = subparsers.add_parser(
        "eval",
        help="evaluate on TAP-Vid (DAVIS, Kinetics, RGB-Stacking, RoboTAP) or Kubric data",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--dataset", required=True, choices=DATASETS)
    parser.add_argument(
        "--root",
        required=True,
        help="the dataset file, or a folder laid out as CoTracker's "
        "(tapvid_davis/tapvid_davis.pkl, tapvid_kinetics/*_of_0010.pkl, ...); "
        "for kubric the folder of sequence folders",
    )
    parser.add_argument(
        "--mode",
        choices=QUERY_MODES,
        default="first",
        help="first: query each track on its first visible frame, score later frames; "
        "strided: query every 5th frame, score all other frames (default: first)",
    )
    parser.add_argument(
        "--tracker",
        choices=TRACKERS,
        default="taptr",
        help="taptr: the model; static: points never move; lk: OpenCV Lucas-Kanade "
        "(default: taptr)",
    )
    _add_model_arguments(parser)
    parser.add_argument("--protocol", choices=PROTOCOLS, default="standard")
    parser.add_argument("--max-videos", type=int, metavar="N", help="score only the first N videos")
    parser.add_argument(
        "--overlays",
        type=int,
        default=0,
        metavar="K",
        help="write ground truth | prediction overlay videos of the K worst videos "
        "to OUT/overlays/",
    )
    add_device_argument(parser)
    parser.add_argument("--out", required=True, help="output folder")
    parser.set_defaults(func=run)


def _add_model_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of the model the standard protocol runs."""
    from taptr.types import AUTOCAST_TYPES

    parser.add_argument(
        "--checkpoint",
        help="for --tracker taptr, and required by --protocol official: a " + CHECKPOINT_HELP,
    )
    parser.add_argument(
        "--context-points",
        type=int,
        default=None,
        metavar="K",
        help="standard protocol: pad each video's queries with seeded context points up to "
        "K points (default: the model's, 800 for the paper's weights; 0: none)",
    )
    parser.add_argument(
        "--support",
        choices=SUPPORT_CHOICES,
        default="auto",
        help="standard protocol: the predictor's extra points around the queries (as "
        "taptr track --support; default: auto, the model's own)",
    )
    parser.add_argument(
        "--points-per-call",
        type=int,
        default=None,
        metavar="G",
        help="standard protocol: track each video's queries in groups of G points, one "
        "model call each, as a user clicking a few points would (default: all at once)",
    )
    parser.add_argument(
        "--dtype",
        choices=AUTOCAST_TYPES,
        default="float32",
        help="standard protocol: run the model under autocast in this type (weights in "
        "float32; for GPUs) (default: float32, no autocast)",
    )


def run(args: argparse.Namespace) -> int:
    """Evaluates and prints the table from the main process."""
    from taptr.eval.runner import EvalConfig, run_evaluation

    check_output_folder(args.out)
    check_device(args.device)
    check_input_path(args.root, "--root")
    check_at_least(args.max_videos, 1, "--max-videos")
    check_at_least(args.overlays, 0, "--overlays")
    check_at_least(args.context_points, 0, "--context-points")
    check_at_least(args.points_per_call, 1, "--points-per-call")
    config = EvalConfig(
        dataset=args.dataset,
        root=args.root,
        mode=args.mode,
        tracker=args.tracker,
        protocol=args.protocol,
        checkpoint=args.checkpoint,
        max_videos=args.max_videos,
        device=args.device,
        overlays=args.overlays,
        context_points=args.context_points,
        support_points=None if args.support == "auto" else args.support,
        points_per_call=args.points_per_call,
        dtype=args.dtype,
    )
    try:
        outcome = run_evaluation(config, args.out, progress=True)
    except pickle.UnpicklingError as error:
        # a dataset file that is not plain data (or not a pickle): one line, no traceback
        raise ValueError(str(error)) from None
    if outcome.is_main:
        from taptr.eval.report import format_table

        report = outcome.report
        print(
            f"{report['dataset']} {report['mode']}, {report['tracker']} "
            f"({report['protocol']} protocol), {len(report['videos'])} videos"
        )
        print(format_table(report))
        for path in outcome.files:
            print(f"wrote {path}")
    return 0
