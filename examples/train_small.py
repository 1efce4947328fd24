"""Train a small model on generated videos: ``taptr make-synthetic`` and ``taptr train``, in Python.

    python examples/train_small.py                         # small preset, 200 steps, CPU
    python examples/train_small.py --steps 1700 --videos 300   # the bundled model's recipe
    python examples/train_small.py --data my_clips --init-from taptrv2.pth --preset taptrv2

Writes procedural training videos with exact tracks (Kubric layout) unless ``--data`` names
your own folder in that layout (check it first with ``taptr check-data``), trains with the
`small` recipe and ``KEY=VALUE`` overrides as ``taptr train`` takes them, then tracks the
sample clip with the result. ``--init-from`` fine-tunes from existing weights (a taptr
checkpoint or the authors' release). docs/TRAINING.md explains the recipe and multi-GPU runs.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="runs/example", help="run folder")
    parser.add_argument("--data", help="Kubric-layout training folder (default: generate one)")
    parser.add_argument("--videos", type=int, default=50, help="videos to generate")
    parser.add_argument("--size", type=int, default=128, help="side of generated videos")
    parser.add_argument("--steps", type=int, default=200, help="optimizer steps")
    parser.add_argument("--preset", default="small", help="model preset: small, tiny, taptrv2")
    parser.add_argument("--init-from", help="start from these weights (fine-tuning)")
    parser.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="more config changes")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Generates data, trains, tracks the sample clip with the trained weights."""
    args = parse_args(argv)
    import taptr
    from taptr.data.sample_video import make_sample_clip
    from taptr.data.synthetic import SyntheticConfig, write_dataset
    from taptr.train.config import load_config
    from taptr.train.loop import train

    out = Path(args.out)
    data = args.data
    if data is None:
        data = str(out / "data")
        frames = 16
        config = SyntheticConfig(height=args.size, width=args.size, num_frames=frames)
        write_dataset(data, args.videos, config)
        print(f"wrote {args.videos} synthetic videos to {data}")
    overrides = [
        "preset=small",  # the recipe of the bundled model: 16-frame clips, 128 points
        f"model.preset={args.preset}",
        f"data.root={data}",
        "data.val_root=",  # no held-out set in this example
        f"data.frame_size=[{args.size},{args.size}]",
        "data.num_workers=0",
        f"steps={args.steps}",
        f"lr_milestones=[{int(args.steps * 0.8)}]",
        f"out_dir={out}",
        f"log_every={max(1, args.steps // 10)}",
        *([f"init_from={args.init_from}"] if args.init_from else []),
        *args.overrides,
    ]
    model_path = train(load_config(None, overrides))
    print(f"trained {args.steps} steps: {model_path}")

    predictor = taptr.Predictor.from_pretrained(model_path, device="cpu")
    clip = make_sample_clip(num_frames=16)
    result = predictor.track(clip.video, grid_size=4)
    print(f"tracked a 4x4 grid through the sample clip: tracks {tuple(result.tracks.shape)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
