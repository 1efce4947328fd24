"""TAPTRv3's per-frame decoder, eager against ``torch.compile`` (Inductor), on this machine.

Frames are encoded once beforehand; only the decoding of each frame is timed, in the
static-shape step (`taptr.model.v3.per_frame.FrameState.static_shapes`) for both, so the
compiled decoder is traced once per history buffer size. Compilation is timed apart.

    python benchmarks/compiled_step.py --size 128 128 --points 800 --frames 12
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from taptr.apps.benchmark import machine
from taptr.model.build import build_model
from taptr.model.sliding_window import QuerySet
from taptr.model.taptr import normalize_frames
from taptr.model.v3.per_frame import run_frames
from taptr.runtime.frames import PrecomputedFrames


def decode(model, features, queries, frames: int) -> tuple[float, torch.Tensor]:
    start = time.perf_counter()
    with torch.no_grad():
        out = run_frames(model, queries, frames, features, torch.float32, static_shapes=True)
    return (time.perf_counter() - start) / frames, out.positions


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--preset", default="taptrv3")
    parser.add_argument("--size", type=int, nargs=2, default=(128, 128))
    parser.add_argument("--points", type=int, default=800)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = build_model(args.preset).eval()
    video = torch.rand(1, args.frames, 3, *args.size)
    queries = QuerySet(
        torch.zeros(1, args.points, dtype=torch.long),
        torch.rand(1, args.points, 2) * 0.9 + 0.05,
        torch.ones(1, args.points, dtype=torch.bool),
    )
    with torch.no_grad():
        features = PrecomputedFrames(model.encode(normalize_frames(video)))
    decode(model, features, queries, args.frames)  # warm: tables, allocator
    eager = min(decode(model, features, queries, args.frames)[0] for _ in range(2))
    _, reference = decode(model, features, queries, args.frames)
    model.decoder.compile(fullgraph=True)
    start = time.perf_counter()
    decode(model, features, queries, args.frames)  # compiles (once per buffer size)
    first = time.perf_counter() - start
    compiled, positions = min(
        (decode(model, features, queries, args.frames) for _ in range(2)), key=lambda r: r[0]
    )
    result = {
        "preset": args.preset,
        "size": args.size,
        "points": args.points,
        "frames": args.frames,
        "eager_decoder_seconds_per_frame": eager,
        "compiled_decoder_seconds_per_frame": compiled,
        "speedup": eager / compiled,
        "first_compiled_run_seconds": first,
        # frame 1 only: with random weights, rounding differences grow from frame to frame
        # (oneDNN against BLAS products alone: 4e-6 on frame 1, 0.27 by frame 11)
        "frame_1_max_position_difference": float((positions - reference)[:, 1].abs().max()),
        "machine": machine(),
    }
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
