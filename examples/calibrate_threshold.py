"""Choose and store the visibility threshold of a model: what ``taptr calibrate`` does.

    python examples/calibrate_threshold.py                     # generated labelled clips
    python examples/calibrate_threshold.py --checkpoint my.pth --dataset kubric --root val/

The model gives each point a visibility logit per frame; a point counts as visible where
sigmoid(logit) exceeds a threshold, 0.5 unless the checkpoint stores another. This script
tracks a labelled set once, scores every threshold on those predictions with the metric
``taptr eval`` reports (AJ by default), prints the curve, and writes a copy of the
checkpoint holding the best threshold, which `taptr.Predictor.from_pretrained` then uses.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--checkpoint",
        help="checkpoint file or model name (default: the paper's weights taptrv2-official, "
        "non-commercial licence; offline, the bundled taptr-small-synthetic)",
    )
    parser.add_argument("--dataset", default="kubric", help="davis, kinetics, ..., kubric")
    parser.add_argument("--root", help="labelled set (default: generated sample clips)")
    parser.add_argument("--metric", choices=("aj", "oa"), default="aj")
    parser.add_argument("--videos", type=int, default=3, help="size of the generated set")
    parser.add_argument("--out", default="outputs/calibrated.pth", help="checkpoint to write")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Tracks once, scores the thresholds, writes the checkpoint."""
    args = parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="taptr-example-") as scratch:
        return run(args, Path(scratch))


def run(args: argparse.Namespace, scratch: Path) -> int:
    """`main` with a scratch folder for the generated labelled clips, removed afterwards."""
    import numpy as np

    import taptr
    from taptr.data.kubric import write_sequence
    from taptr.data.sample_video import make_sample_clip
    from taptr.eval.calibrate import choose_threshold, predict_videos, write_calibrated
    from taptr.eval.datasets import open_dataset
    from taptr.types import TrackingSample

    root = args.root
    if root is None:
        root = scratch / "labelled"
        for seed in range(args.videos):
            clip = make_sample_clip(num_frames=16, seed=seed)
            grid = np.linspace(20, 235, 5)
            queries = np.array([[0, x, y] for y in grid for x in grid])
            tracks, visible = clip.track(queries)  # exact ground truth of the sample clip
            write_sequence(root / f"{seed:05d}", TrackingSample(clip.video, tracks, visible))
    predictor = taptr.Predictor.from_pretrained(args.checkpoint, device="cpu")
    predictions = predict_videos(predictor, open_dataset(args.dataset, root), "first")
    result = choose_threshold(
        predictions, metric=args.metric, current=predictor.visibility_threshold
    )
    for threshold, score in zip(result.thresholds, result.scores, strict=True):
        bar = "#" * round(40 * score)
        print(f"{threshold:5.2f} {100 * score:5.1f} {bar}")
    path = write_calibrated(args.checkpoint, args.out, result.threshold)
    print(
        f"best threshold {result.threshold:.2f} ({args.metric.upper()} {100 * result.score:.1f}"
        f", was {100 * result.current_score:.1f} at {result.current:.2f}); wrote {path}"
    )
    stored = taptr.Predictor.from_pretrained(path, device="cpu").visibility_threshold
    print(f"Predictor.from_pretrained({str(path)!r}).visibility_threshold == {stored:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
