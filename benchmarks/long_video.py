"""Memory and time of ``taptr track`` on a long video: is the whole pipeline flat in length?

    python benchmarks/long_video.py --frames 600 --size 360 640 --points 100

Makes a clip of FRAMES frames (the sample generator's 48-frame clip, repeated, at the given
size; cached under runs/bench/), then, each in its own process and measured with
``os.wait4`` (peak RSS of that process alone):

1. ``taptr track CLIP --grid G --max-frames 60`` (the first 60 frames),
2. ``taptr track CLIP --grid G`` (all of it),
3. decoding + drawing + encoding alone: the same frames decoded, drawn with the tracks of
   run 2 and encoded, without the model (the share of the pipeline that is not tracking).

With ``--backward`` the points are placed on frame 30 and tracked both ways, so the file is
also read backwards, segment by segment.

Prints a table and writes benchmarks/results/long-video-FRAMES.json.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def make_clip(path: Path, frames: int, height: int, width: int) -> Path:
    """A long clip: the 48-frame sample clip at (height, width), repeated."""
    from taptr.data.sample_video import make_sample_clip
    from taptr.io.video import write_video

    if path.is_file():
        return path
    base = make_sample_clip(num_frames=48, height=height, width=width).video
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_video(path, (base[t % len(base)] for t in range(frames)), fps=24.0)


def measured(command: list[str]) -> tuple[float, float]:
    """(seconds, peak RSS in GB) of one child process."""
    started = time.perf_counter()
    child = subprocess.Popen(command, stdout=subprocess.DEVNULL)
    _, status, usage = os.wait4(child.pid, 0)
    if status:
        raise SystemExit(f"failed ({status}): {' '.join(command)}")
    return time.perf_counter() - started, usage.ru_maxrss * 1024 / 1e9


def io_only(clip: Path, tracks_npz: Path, out: Path) -> None:
    """Decode, draw and encode with saved tracks, no model (run in its own process)."""
    import numpy as np

    from taptr.api.streaming import FinalFrames, draw_final
    from taptr.io.tracks import load_tracks_npz
    from taptr.io.video import iter_frames, write_video

    saved = load_tracks_npz(tracks_npz)

    def batches():
        for index, frame in enumerate(iter_frames(clip)):
            yield FinalFrames(
                index,
                frame[None],
                saved.tracks[index : index + 1],
                saved.visibility[index : index + 1],
                np.zeros((1, saved.tracks.shape[1]), np.float32),
            )

    write_video(out, draw_final(batches(), saved.queries.astype(np.float32)), 24.0)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=600, help="clip length (default 600)")
    parser.add_argument("--size", type=int, nargs=2, default=(360, 640), metavar=("H", "W"))
    parser.add_argument("--points", type=int, default=100, help="points, as a grid (default 100)")
    parser.add_argument("--checkpoint", default="taptr-small-synthetic", help="model to run")
    parser.add_argument("--work", type=Path, default=Path("runs/bench"), help="scratch folder")
    parser.add_argument(
        "--backward",
        action="store_true",
        help="points on frame 30, tracked both ways (the file is read a second time, backwards)",
    )
    parser.add_argument(
        "--io-only", nargs=3, metavar=("CLIP", "NPZ", "OUT"), help=argparse.SUPPRESS
    )
    args = parser.parse_args()
    if args.io_only:
        io_only(*map(Path, args.io_only))
        return 0
    height, width = args.size
    clip = make_clip(
        args.work / f"long-{args.frames}-{height}x{width}.mp4", args.frames, height, width
    )
    grid = str(math.isqrt(args.points))
    track = ["taptr", "track", str(clip), "--grid", grid, "--checkpoint", args.checkpoint]
    if args.backward:
        track += ["--backward", "--query-frame", "30"]
    rows = {}
    short = args.work / "out-60"
    rows["first 60 frames"] = measured([*track, "--max-frames", "60", "--out", str(short)])
    full = args.work / f"out-{args.frames}"
    rows[f"all {args.frames} frames"] = measured([*track, "--out", str(full)])
    rows["decode + draw + encode only"] = measured(
        [sys.executable, __file__, "--io-only", str(clip), str(full / "tracks.npz"),
         str(args.work / "io-only.mp4")]
    )  # fmt: skip
    both_ways = ", on frame 30, --backward" if args.backward else ""
    print(f"{args.frames} frames of {width}x{height}, {int(grid) ** 2} points{both_ways}, ", end="")
    print(args.checkpoint)
    print("| run | seconds | peak RSS |\n|---|---:|---:|")
    for name, (seconds, rss) in rows.items():
        print(f"| {name} | {seconds:.1f} | {rss:.2f} GB |")
    full_time, full_rss = rows[f"all {args.frames} frames"]
    short_rss = rows["first 60 frames"][1]
    io_time = rows["decode + draw + encode only"][0]
    print(f"peak RSS, all / first 60: {full_rss / short_rss:.3f}")
    print(f"decode + draw + encode share of the full run: {io_time / full_time:.1%}")
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / f"long-video-{args.frames}{'-backward' if args.backward else ''}.json"
    out.write_text(
        json.dumps({"args": vars(args) | {"work": str(args.work)}, "rows": rows}, indent=1)
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
