"""TAPTRv3's per-frame decoder, eager against ``torch.compile`` (Inductor), on this machine.

Frames are encoded once beforehand; only the decoding of each frame is timed, in the
static-shape step (`taptr.model.v3.per_frame.DecoderStep.static_shapes`) for both; the
compiled one is the step the predictor captures (`taptr.runtime.step_capture`), compiled
once for every history buffer size. Compilation is timed apart: a
second run of the same command reads what Inductor keeps on disk and shows what a later
process pays. ``--dtype bfloat16`` runs both under the predictor's CPU bfloat16
(`taptr.runtime.precision.precision_context`).

    python benchmarks/compiled_step.py --size 128 128 --points 800 --frames 12
    python benchmarks/compiled_step.py --size 384 512 --frames 8 --dtype bfloat16
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import torch

from taptr.apps.benchmark import machine
from taptr.model.build import build_model
from taptr.model.taptr import normalize_frames
from taptr.model.trajectory import QuerySet
from taptr.model.v3.per_frame import run_frames
from taptr.runtime.frames import PrecomputedFrames
from taptr.runtime.precision import precision_context
from taptr.runtime.step_capture import StepCapture


def decode(
    model, features, queries, frames: int, autocast=None, capture: str = "off"
) -> tuple[float, torch.Tensor]:
    """Seconds per frame of decoding ``frames`` frames, and the positions.

    ``capture="on"``: the step the predictor replays (`taptr.runtime.step_capture`).
    """
    points = queries.start_frames.shape[1]
    # eager: the model's decoder on static shapes; captured: the step, static as it replays
    static: dict[str, Any] = {"static_shapes": True}
    if capture == "on":
        step = StepCapture(model.decoder, torch.device("cpu"), "on", str, points, frames)
        static = {"step": step}
    start = time.perf_counter()
    with torch.no_grad(), precision_context("cpu", autocast):
        out = run_frames(model, queries, frames, features, torch.float32, **static)
    return (time.perf_counter() - start) / frames, out.positions


def main() -> None:
    """Times the decoder eager and compiled and prints one JSON object."""
    parser = argparse.ArgumentParser()
    parser.add_argument("--preset", default="taptrv3")
    parser.add_argument("--size", type=int, nargs=2, default=(128, 128))
    parser.add_argument("--points", type=int, default=800)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32")
    args = parser.parse_args()
    autocast = torch.bfloat16 if args.dtype == "bfloat16" else None
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = build_model(args.preset).eval()
    if autocast is not None:
        model.bfloat16_trunk()
    video = torch.rand(1, args.frames, 3, *args.size)
    queries = QuerySet(
        torch.zeros(1, args.points, dtype=torch.long),
        torch.rand(1, args.points, 2) * 0.9 + 0.05,
        torch.ones(1, args.points, dtype=torch.bool),
    )
    with torch.no_grad(), precision_context("cpu", autocast):
        features = PrecomputedFrames(model.encode(normalize_frames(video)))
    decode(model, features, queries, args.frames, autocast)  # warm: tables, allocator
    eager = min(decode(model, features, queries, args.frames, autocast)[0] for _ in range(2))
    _, reference = decode(model, features, queries, args.frames, autocast)
    start = time.perf_counter()
    decode(model, features, queries, args.frames, autocast, "on")  # compiles
    first = time.perf_counter() - start
    runs = [decode(model, features, queries, args.frames, autocast, "on") for _ in range(2)]
    compiled, positions = min(runs, key=lambda r: r[0])
    result = {
        "preset": args.preset,
        "size": args.size,
        "points": args.points,
        "frames": args.frames,
        "dtype": args.dtype,
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
