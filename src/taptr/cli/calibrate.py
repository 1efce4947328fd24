"""``taptr calibrate``: choose the visibility threshold on a labelled set and store it."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from taptr.cli.common.model_options import CHECKPOINT_HELP, check_checkpoint_name
from taptr.cli.common.options import (
    add_device_argument,
    check_at_least,
    check_device,
    check_input_path,
    check_output_file,
)

DESCRIPTION = """\
Tracks every video of a labelled set once, then scores visibility thresholds 0.05, 0.10,
..., 0.95 (and the model's current one) on those predictions with the TAP-Vid metric of
'taptr eval' (standard protocol), and writes a copy of the checkpoint that stores the best
threshold. taptr.Predictor.from_pretrained (and every command) then uses it for that file.
Calibrate on data like the data you will track, and not on the set you report results on.
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    from taptr.eval.datasets import DATASETS
    from taptr.eval.metrics import CALIBRATION_METRICS as METRICS
    from taptr.eval.metrics import QUERY_MODES

    parser = subparsers.add_parser(
        "calibrate",
        help="pick the visibility threshold that maximises AJ (or OA) and store it",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--checkpoint",
        help=CHECKPOINT_HELP,
    )
    parser.add_argument("--dataset", required=True, choices=DATASETS, help="labelled set")
    parser.add_argument(
        "--root", required=True, help="dataset file or folder, as for 'taptr eval --root'"
    )
    parser.add_argument("--mode", choices=QUERY_MODES, default="first", help="query mode")
    parser.add_argument(
        "--metric",
        choices=tuple(METRICS),
        default="aj",
        help="aj: average Jaccard; oa: occlusion accuracy (default: aj)",
    )
    parser.add_argument(
        "--thresholds",
        type=float,
        nargs="+",
        metavar="P",
        help="candidate thresholds in (0, 1) (default: 0.05 0.10 ... 0.95)",
    )
    parser.add_argument("--max-videos", type=int, metavar="N", help="use only the first N videos")
    add_device_argument(parser)
    parser.add_argument(
        "--out", required=True, help="checkpoint to write (may be a taptr --checkpoint file itself)"
    )
    parser.add_argument("--json", metavar="FILE", help="also write every score to this JSON file")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Calibrates, prints the scores and writes the checkpoint."""
    check_at_least(args.max_videos, 1, "--max-videos")
    check_output_file(args.out)
    check_input_path(args.root, "--root")
    check_checkpoint_name(args.checkpoint)
    if args.json:
        check_output_file(args.json, "--json")
    check_device(args.device)  # imports torch for a GPU: after the cheap checks
    from taptr.api.predictor import Predictor
    from taptr.eval.calibrate import (
        DEFAULT_THRESHOLDS,
        choose_threshold,
        predict_videos,
        write_calibrated,
    )
    from taptr.eval.datasets import open_dataset

    thresholds = tuple(args.thresholds) if args.thresholds else DEFAULT_THRESHOLDS
    predictor = Predictor.from_pretrained(args.checkpoint, device=args.device)
    predictions = predict_videos(
        predictor,
        open_dataset(args.dataset, args.root),
        args.mode,
        max_videos=args.max_videos,
        progress=True,
    )
    result = choose_threshold(
        predictions,
        metric=args.metric,
        query_mode=args.mode,
        thresholds=thresholds,
        current=predictor.visibility_threshold,
    )
    name = args.metric.upper()
    print(f"{result.num_videos} videos, {args.dataset} {args.mode}; {name} by threshold:")
    for threshold, score in zip(result.thresholds, result.scores, strict=True):
        marks = [
            m
            for t, m in ((result.threshold, "best"), (result.current, "current"))
            if t == threshold
        ]
        print(f"  {threshold:5.2f}  {100 * score:6.2f}  {' '.join(marks)}")
    path = write_calibrated(args.checkpoint, args.out, result.threshold)
    print(
        f"threshold {result.threshold:.2f}: {name} {100 * result.score:.2f} "
        f"(was {result.current:.2f}: {100 * result.current_score:.2f}); wrote {path}"
    )
    if args.json:
        report = {"checkpoint": args.checkpoint, "dataset": args.dataset, **result.to_dict()}
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(report, indent=2) + "\n")
    return 0
