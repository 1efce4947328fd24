"""Measure tracking speed and memory on your machine: a small ``taptr bench``, in Python.

    python examples/benchmark.py                             # small preset, CPU, 2 threads
    python examples/benchmark.py --preset taptrv2 --points 100 800 --frames 24 --device cuda

Times `taptr.Predictor.track` on a random video (the cost does not depend on the pixels)
for each number of points, after one warm-up run, and reports seconds per frame and peak
memory (resident set size of the process on CPU, allocated tensor memory on CUDA). Weights
are random too: speed does not depend on them. ``taptr bench`` goes further (the reference
and fast executions side by side, a per-stage breakdown, FLOPs); docs/BENCHMARKS.md has figures.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="small", help="taptrv2, small, tiny (default small)")
    parser.add_argument("--frames", type=int, default=24, help="frames T (default 24)")
    parser.add_argument("--points", type=int, nargs="+", default=[64, 256], help="values of N")
    parser.add_argument("--size", type=int, nargs=2, default=(256, 256), metavar=("H", "W"))
    parser.add_argument("--device", default="cpu", help="cpu, cuda, mps (default cpu)")
    parser.add_argument("--threads", type=int, default=2, help="CPU threads (default 2)")
    return parser.parse_args(argv)


def peak_memory_mb(device: str) -> float:
    """Peak memory so far: CUDA allocations, or the process's resident set on CPU."""
    import torch

    if device.startswith("cuda"):
        return torch.cuda.max_memory_allocated() / 2**20
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux


def main(argv: Sequence[str] | None = None) -> int:
    """Times each N and prints a table."""
    args = parse_args(argv)
    import numpy as np
    import torch

    import taptr

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    predictor = taptr.Predictor(taptr.build_model(args.preset), device=args.device)
    height, width = args.size
    rng = np.random.default_rng(0)
    video = rng.integers(0, 256, (args.frames, height, width, 3), dtype=np.uint8)
    print(
        f"{args.preset} at {predictor.input_size}, {args.frames} frames of {width}x{height}, "
        f"{args.device}, {args.threads} threads"
    )
    print(f"{'points':>7} {'s/frame':>8} {'peak MB':>8}")
    for points in args.points:
        queries = np.column_stack(
            [
                np.zeros(points),
                rng.uniform(0, width - 1, points),
                rng.uniform(0, height - 1, points),
            ]
        )
        predictor.track(video[: min(args.frames, 8)], queries)  # warm-up: allocations, kernels
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        start = time.perf_counter()
        predictor.track(video, queries)
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()
        seconds = (time.perf_counter() - start) / args.frames
        print(f"{points:7d} {seconds:8.3f} {peak_memory_mb(args.device):8.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
