"""Write the generated sample clip and its exact ground truth: ``taptr sample-video``, and more.

    python examples/sample_video.py                     # outputs/sample.mp4 + ground truth
    python examples/sample_video.py --frames 96 --size 360 640 --out clip.mp4

The clip is drawn by taptr itself (no data file, no download, no licence question): a
textured scene under a known camera pan, zoom and roll, and a textured disc that rolls
across it and occludes the background. Because both motions are known, `SampleClip.track`
gives the true track and visibility of any query point, which makes the clip a test
video with an answer key. This script writes the clip, the ground truth of a grid of
points queried on frame 0 (``.npz`` and ``.csv``, the formats ``taptr track`` writes),
and a drawing of that ground truth.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="outputs/sample.mp4", help="output mp4")
    parser.add_argument("--frames", type=int, default=48, help="number of frames (default 48)")
    parser.add_argument("--size", type=int, nargs=2, default=(256, 256), metavar=("H", "W"))
    parser.add_argument("--seed", type=int, default=0, help="seed of the textures")
    parser.add_argument("--grid", type=int, default=8, help="N×N ground-truth points")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Writes the clip, the ground truth and its drawing."""
    args = parse_args(argv)
    import numpy as np

    from taptr.data.sample_video import make_sample_clip
    from taptr.io.tracks import save_tracks_csv, save_tracks_npz
    from taptr.io.video import write_video
    from taptr.viz.draw import draw_tracks

    height, width = args.size
    clip = make_sample_clip(num_frames=args.frames, height=height, width=width, seed=args.seed)
    out = Path(args.out)
    write_video(out, clip.video, clip.fps)

    xs = np.linspace(0.05 * (width - 1), 0.95 * (width - 1), args.grid)
    ys = np.linspace(0.05 * (height - 1), 0.95 * (height - 1), args.grid)
    queries = np.array([[0, x, y] for y in ys for x in xs], np.float32)  # (t, x, y)
    tracks, visible = clip.track(queries)  # (T, N, 2) pixels, (T, N) True = visible
    stem = out.with_suffix("")
    save_tracks_npz(f"{stem}_truth.npz", tracks, visible, queries, {"source": "SampleClip"})
    save_tracks_csv(f"{stem}_truth.csv", tracks, visible)
    write_video(f"{stem}_truth.mp4", draw_tracks(clip.video, tracks, visible), clip.fps)

    occluded = (~visible).any(axis=0).sum()
    print(f"wrote {out} ({args.frames} frames, {width}x{height}, {clip.fps:g} fps)")
    print(
        f"ground truth of {len(queries)} points, {occluded} of them occluded at some point: "
        f"{stem}_truth.npz, {stem}_truth.csv, {stem}_truth.mp4"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
