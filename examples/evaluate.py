"""Score trackers with the TAP-Vid metrics: what ``taptr eval`` does, in Python.

    python examples/evaluate.py                  # a generated labelled set, taptr vs baselines
    python examples/evaluate.py --dataset davis --root data/tapvid --checkpoint taptrv2.pth
    python examples/evaluate.py --dataset kubric --root my_labelled_clips --mode strided

Without ``--root``, a small labelled set is generated first: sample clips (whose true
tracks are known exactly) written in the Kubric layout, which is also the layout for your
own annotated videos (`taptr.data.kubric.write_sequence`). Every tracker is scored with
the canonical protocol (videos resized to 256 × 256, queries in ``first`` or ``strided``
mode, tapnet's metric) and the mean over videos is printed: AJ (average Jaccard), <δavg
(position accuracy) and OA (occlusion accuracy), in percent.
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
    parser.add_argument("--dataset", default="kubric", help="davis, kinetics, ..., kubric")
    parser.add_argument("--root", help="dataset file or folder (default: a generated set)")
    parser.add_argument("--mode", choices=("first", "strided"), default="first")
    parser.add_argument(
        "--checkpoint",
        help="checkpoint file or model name (default: the paper's weights taptrv2-official, "
        "non-commercial licence; offline, the bundled taptr-small-synthetic)",
    )
    parser.add_argument("--device", help="cpu, cuda, mps (default: cuda if available)")
    parser.add_argument("--max-videos", type=int, help="score only the first N videos")
    parser.add_argument("--videos", type=int, default=3, help="size of the generated set")
    parser.add_argument("--frames", type=int, default=24, help="frames per generated video")
    return parser.parse_args(argv)


def generate_set(root: Path, videos: int, frames: int) -> None:
    """Sample clips with exact tracks of a 6×6 grid queried on frame 0, Kubric layout."""
    import numpy as np

    from taptr.data.kubric import write_sequence
    from taptr.data.sample_video import make_sample_clip
    from taptr.types import TrackingSample

    for seed in range(videos):
        clip = make_sample_clip(num_frames=frames, seed=seed)
        grid = np.linspace(20, 235, 6)
        queries = np.array([[0, x, y] for y in grid for x in grid])
        tracks, visible = clip.track(queries)
        write_sequence(root / f"{seed:05d}", TrackingSample(clip.video, tracks, visible))


def main(argv: Sequence[str] | None = None) -> int:
    """Scores taptr and the two baselines."""
    args = parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="taptr-example-") as scratch:
        return run(args, Path(scratch))


def run(args: argparse.Namespace, scratch: Path) -> int:
    """`main` with a scratch folder for the generated labelled clips, removed afterwards."""
    from taptr.eval.baselines import LucasKanadeTracker, StaticTracker
    from taptr.eval.datasets import open_dataset
    from taptr.eval.metrics import mean_over_videos
    from taptr.eval.predictor_tracker import PredictorTracker
    from taptr.eval.protocols import StandardProtocol
    from taptr.eval.runner import evaluate

    root = args.root
    if root is None:
        root = str(scratch / "labelled")
        generate_set(Path(root), args.videos, args.frames)
        print(f"generated {args.videos} labelled sample clips in {root}")
    trackers = {
        # the predictor tracks backwards itself when strided mode scores earlier frames
        "taptr": PredictorTracker.from_pretrained(
            args.checkpoint, backward=args.mode == "strided", device=args.device
        ),
        "static": StaticTracker(),
        "lk": LucasKanadeTracker(),
    }
    print(f"{'tracker':8} {'AJ':>6} {'<δavg':>6} {'OA':>6}   ({args.dataset}, {args.mode})")
    for name, tracker in trackers.items():
        videos = open_dataset(args.dataset, root)  # read lazily, one video at a time
        results = evaluate(StandardProtocol(tracker), videos, args.mode, max_videos=args.max_videos)
        mean = mean_over_videos([r.metrics for r in results])
        aj, delta, oa = (
            100 * mean[k]
            for k in ("average_jaccard", "average_pts_within_thresh", "occlusion_accuracy")
        )
        print(f"{name:8} {aj:6.1f} {delta:6.1f} {oa:6.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
