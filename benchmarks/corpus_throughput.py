"""Throughput of ``taptr track-corpus`` with 1 and 2 actors, and the GPU-hours of a corpus.

Writes ``--videos`` generated clips, then for each actor count runs `track_corpus` on a
local Ray instance into a fresh folder and reports the wall time (actor start-up
included), videos and frames per second, and the actor-seconds per frame (time the
actors spent on the videos: decoding, tracking, writing). The same clips are also tracked
in this process with `taptr.api.streaming.track_frames` (no Ray) for the overhead.

The GPU-hours of a corpus are estimated, not measured: frames × seconds per frame / 3600,
for a million 10-second clips at 30 fps (``--clips``, ``--clip-seconds``, ``--fps``), with
the seconds per frame measured here and those given by ``--gpu-seconds-per-frame`` (GPU
figures measured by ``taptr bench`` and benchmarks/gpu_executions.py, docs/BENCHMARKS.md).

    python benchmarks/corpus_throughput.py --videos 8 --frames 24 --size 96 128 --grid 4
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--videos", type=int, default=8)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--size", type=int, nargs=2, default=(96, 128), metavar=("H", "W"))
    parser.add_argument("--grid", type=int, default=4)
    parser.add_argument("--model", default="tiny", help="model name or checkpoint")
    parser.add_argument("--actors", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--cpus", type=int, default=2, help="CPUs of the local Ray instance")
    parser.add_argument("--clips", type=float, default=1e6)
    parser.add_argument("--clip-seconds", type=float, default=10.0)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument(
        "--gpu-seconds-per-frame",
        nargs="*",
        default=[],
        metavar="NAME=SECONDS",
        help="measured GPU figures to estimate with, e.g. h200-bf16=0.0269",
    )
    parser.add_argument("--json", help="also write the results here")
    args = parser.parse_args()

    import ray

    from taptr.api.spec import ModelSpec
    from taptr.corpus.pipeline import CorpusOptions, run_corpus

    folder = Path(tempfile.mkdtemp(prefix="corpus-bench-"))
    videos = _write_clips(folder, args)
    model = ModelSpec(args.model, device="cpu", input_size=tuple(args.size))
    results: dict = {
        "command": "python benchmarks/corpus_throughput.py " + " ".join(sys.argv[1:]),
        "cpu": _cpu_name(),
        "load_average_before": os.getloadavg(),
        "videos": len(videos),
        "frames_per_video": args.frames,
        "in_process_seconds_per_frame": _in_process(model.load, videos, args.frames),
        "runs": [],
    }
    os.environ.setdefault("RAY_memory_monitor_refresh_ms", "0")  # shared machines
    ray.init(address="local", num_cpus=args.cpus, include_dashboard=False, log_to_driver=False)
    for actors in args.actors:
        options = CorpusOptions(
            out=str(folder / f"out-{actors}"),
            actors=actors,
            cpus_per_actor=max(1, args.cpus // actors),
            progress_every=3600,
        )
        summary = run_corpus(videos, model, options, print_line=lambda *a, **k: None)
        assert summary.done == len(videos), summary.failed
        results["runs"].append(
            {
                "actors": actors,
                "wall_seconds": summary.seconds,
                "videos_per_second": summary.videos_per_second,
                "frames_per_second": summary.frames_per_second,
                "actor_seconds_per_frame": summary.actor_seconds / summary.frames,
                "steady_frames_per_second": actors * summary.frames / summary.actor_seconds,
            }
        )
    ray.shutdown()
    results["load_average_after"] = os.getloadavg()
    results["estimate"] = _estimate(results, args)
    print(json.dumps(results, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")


def _write_clips(folder: Path, args: argparse.Namespace) -> list:
    from taptr.corpus import CorpusVideo, QuerySpec
    from taptr.io.video import write_video

    height, width = args.size
    rng = np.random.default_rng(0)
    videos = []
    for index in range(args.videos):
        frames = np.empty((args.frames, height, width, 3), np.uint8)
        background = rng.integers(0, 256, (height, width + args.frames * 2, 3), np.uint8)
        for t in range(args.frames):  # a textured pan: something to track
            frames[t] = background[:, 2 * t : 2 * t + width]
        path = write_video(folder / f"clip{index:03d}.mp4", frames, fps=args.fps)
        videos.append(CorpusVideo(f"clip{index:03d}", str(path), QuerySpec(grid=args.grid), "b"))
    return videos


def _in_process(make, videos: list, frames: int) -> float:
    """Seconds per frame of streamed tracking in this process, no Ray (after a warm-up)."""
    from taptr.api.inputs import grid_queries
    from taptr.api.streaming import track_frames
    from taptr.io.video import iter_frames, video_info

    predictor = make()
    timed = 0.0
    for index, video in enumerate(videos[:3]):
        info = video_info(video.path)
        queries = grid_queries(video.queries.grid, 0, info.height, info.width).numpy()
        started = time.perf_counter()
        for _ in track_frames(predictor, iter_frames(video.path), queries, num_frames=frames):
            pass
        if index > 0:  # the first video warms up
            timed += time.perf_counter() - started
    return timed / (2 * frames)


def _estimate(results: dict, args: argparse.Namespace) -> dict:
    """GPU-hours (or CPU-actor-hours) of the corpus at each seconds-per-frame figure."""
    frames = args.clips * args.clip_seconds * args.fps
    figures = {
        f"this machine, {run['actors']} actor(s), per actor": run["actor_seconds_per_frame"]
        for run in results["runs"]
    }
    for entry in args.gpu_seconds_per_frame:
        name, _, seconds = entry.partition("=")
        figures[name] = float(seconds)
    return {
        "frames": frames,
        "hours": {name: frames * seconds / 3600 for name, seconds in figures.items()},
    }


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip() + f" ({os.cpu_count()} cores)"
    except OSError:
        pass
    return platform.processor()


if __name__ == "__main__":
    main()
