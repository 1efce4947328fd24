"""Issue 38's GPU cases in one process: TAPTRv3's step eager and replayed, TAPTRv2's predictor.

For a session that is lent a GPU (one run, well under 8 minutes on an H100):

- TAPTRv3 (ResNet-18, 384 × 512, 800 points), float32 and bfloat16 autocast: the decoder
  eager, then compiled with ``mode="reduce-overhead"`` (CUDA graphs of the static step,
  `taptr.model.v3.per_frame.DecoderStep.static_shapes`, replayed every frame), frames
  encoded beforehand; and whole frames (encoder included) eager;
- operations and host syncs per frame on the device (`taptr.runtime.op_count`);
- TAPTRv2 (512 × 512) at 800 and 5,000 points through ``Predictor.track`` (its default
  choices), bfloat16 autocast;
- TAPTRv3 through ``Predictor.track`` with its step captured (``capture="on"``, what
  ``auto`` picks where the kept measurement says so) and not (``"off"``), float32 and
  bfloat16 autocast, frames/s;
- the online tracker's latency per frame (TAPTRv3, 800 points), captured and not;
- TAPTRv3 exported to ONNX (issue 44, `onnx_gpu_cases`): onnxruntime's CUDA provider,
  plain and replayed as CUDA graphs, and its TensorRT provider, float32 and float16,
  encoder and per-frame step with their inputs and outputs bound on the GPU.

Each case runs once untimed first (kernel selection, compilation, graph capture). Weights
are random: the outputs' agreement is checked on frame 1 only (later frames of a random
model are chaotic, docs/BENCHMARKS.md). Prints one JSON object.

    python benchmarks/gpu_lean_step.py --device cuda
    python benchmarks/gpu_lean_step.py --device cpu --preset tiny-v3 --size 64 64 --points 16 \
        --frames 6 --v2-preset tiny --v2-size 64 64 --v2-points 16 --backend eager
    python benchmarks/gpu_lean_step.py --device cpu --preset tiny-v3 --size 64 64 --points 16 \
        --frames 6 --cases onnx_taptrv3  # the ONNX cases alone (the CPU provider without a GPU)
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import sys
import time
from collections.abc import Callable

import numpy as np
import torch

from taptr.api.online import OnlineTracker
from taptr.api.predictor import Predictor
from taptr.apps.benchmark import machine
from taptr.model.build import build_model
from taptr.model.taptr import normalize_frames
from taptr.model.trajectory import QuerySet
from taptr.model.v3.per_frame import run_frames
from taptr.runtime import step_capture
from taptr.runtime.frames import EncodedFrames, PrecomputedFrames
from taptr.runtime.op_count import count_frame_ops
from taptr.runtime.precision import precision_context

TYPES = {"float32": None, "bfloat16": torch.bfloat16}


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def _timed(run: Callable[[], object], device: torch.device) -> tuple[float, object]:
    """Seconds of ``run()`` after one untimed call, and its result."""
    run()
    _sync(device)
    start = time.perf_counter()
    result = run()
    _sync(device)
    return time.perf_counter() - start, result


def _queries(points: int, device: torch.device) -> QuerySet:
    generator = torch.Generator().manual_seed(0)
    return QuerySet(
        torch.zeros(1, points, dtype=torch.long, device=device),
        (torch.rand(1, points, 2, generator=generator) * 0.9 + 0.05).to(device),
        torch.ones(1, points, dtype=torch.bool, device=device),
    )


def v3_cases(args: argparse.Namespace, device: torch.device) -> dict[str, object]:
    """TAPTRv3 per frame: decoder eager and replayed, whole frames eager, per dtype."""
    torch.manual_seed(0)
    model = build_model(args.preset).eval().to(device)
    video = torch.rand(1, args.frames, 3, *args.size, device=device)
    queries = _queries(args.points, device)
    results: dict[str, object] = {}
    types = TYPES if device.type == "cuda" else {"float32": None}
    for name, autocast in types.items():
        context = precision_context(device.type, autocast) if device.type == "cuda" else None
        with torch.no_grad(), context or contextlib.nullcontext():
            features = PrecomputedFrames(model.encode(normalize_frames(video)))

            def decode(net: torch.nn.Module = model, features=features) -> torch.Tensor:
                out = run_frames(net, queries, args.frames, features, torch.float32)
                return out.positions

            def whole() -> torch.Tensor:
                frames = EncodedFrames(model, lambda a, b: normalize_frames(video[:, a : b + 1]), 1)
                return run_frames(model, queries, args.frames, frames, torch.float32).positions

            eager, positions = _timed(decode, device)
            whole_seconds, _ = _timed(whole, device)
            replayed_model = copy.deepcopy(model)
            if args.backend == "inductor":  # CUDA graphs where there is CUDA
                replayed_model.decoder.compile(mode="reduce-overhead", fullgraph=True)
            else:
                replayed_model.decoder.compile(backend=args.backend, fullgraph=True)
            start = time.perf_counter()
            decode(replayed_model)  # compiles and captures
            _sync(device)
            first = time.perf_counter() - start
            replayed, replayed_positions = _timed(lambda net=replayed_model: decode(net), device)
        results[name] = {
            "decoder_eager_fps": args.frames / eager,
            "decoder_replayed_fps": args.frames / replayed,
            "first_replayed_run_seconds": first,
            "whole_frame_eager_fps": args.frames / whole_seconds,
            "frame_1_max_position_difference": float(
                (replayed_positions - positions)[:, 1].abs().max()
            ),
        }
    count = count_frame_ops(model, tuple(args.size), args.points, 6)
    results["ops_per_frame"] = count.per_frame
    results["syncs_per_frame"] = count.syncs_per_frame
    return results


def online_latency(args: argparse.Namespace, device: torch.device) -> dict[str, object]:
    """The online tracker's latency, its step captured and not."""
    return {capture: _online(args, device, capture) for capture in ("off", "on")}


def v3_predictor(args: argparse.Namespace, device: torch.device) -> dict[str, float]:
    """TAPTRv3 through ``Predictor.track``, its step captured and not, frames/s."""
    height, width = args.size
    video = np.random.default_rng(0).integers(0, 256, (args.frames, height, width, 3), np.uint8)
    xy = np.random.default_rng(2).uniform(0, [width - 1, height - 1], (args.points, 2))
    queries = np.concatenate([np.zeros((args.points, 1)), xy], 1).astype(np.float32)
    results = {}
    for name, autocast in TYPES.items():
        for capture in ("off", "on"):
            torch.manual_seed(0)
            predictor = Predictor(
                build_model(args.preset).eval(),
                device=device,
                autocast=autocast,
                capture=capture,
                support_points="none",
            )
            seconds, _ = _timed(lambda p=predictor: p.track(video, queries), device)
            results[f"{name}_capture_{capture}_fps"] = args.frames / seconds
    return results


def _online(args: argparse.Namespace, device: torch.device, capture: str) -> dict[str, float]:
    """Seconds from a frame's arrival to its step's return, TAPTRv3, per frame (median)."""
    torch.manual_seed(0)
    model = build_model(args.preset).eval()
    predictor = Predictor(model, device=device, capture=capture, support_points="none")
    height, width = args.size
    frames = np.random.default_rng(0).integers(0, 256, (args.frames, height, width, 3), np.uint8)
    online = OnlineTracker(predictor)
    state = online.start(frame_size=(height, width))
    grid = np.random.default_rng(1).uniform(0, [width - 1, height - 1], (args.points, 2))
    online.add_queries(state, np.concatenate([np.zeros((args.points, 1)), grid], 1))
    seconds = []
    for frame in frames:
        _sync(device)
        start = time.perf_counter()
        online.step(state, frame)
        _sync(device)
        seconds.append(time.perf_counter() - start)
    online.finish(state)
    later = seconds[2:] or seconds
    return {"median_seconds": float(np.median(later)), "fps": 1 / float(np.median(later))}


def v2_predictor(args: argparse.Namespace, device: torch.device) -> dict[str, float]:
    """TAPTRv2 through ``Predictor.track`` (its own choices), bfloat16 on CUDA, frames/s."""
    torch.manual_seed(0)
    autocast = torch.bfloat16 if device.type == "cuda" else None
    predictor = Predictor(build_model(args.v2_preset).eval(), device=device, autocast=autocast)
    height, width = args.v2_size
    video = np.random.default_rng(0).integers(0, 256, (args.frames, height, width, 3), np.uint8)
    results = {}
    for points in args.v2_points:
        xy = np.random.default_rng(points).uniform(0, [width - 1, height - 1], (points, 2))
        queries = np.concatenate([np.zeros((points, 1)), xy], 1).astype(np.float32)
        seconds, _ = _timed(lambda q=queries: predictor.track(video, q), device)
        results[f"{points}_points_fps"] = args.frames / seconds
    return results


def onnx_taptrv3(args: argparse.Namespace, device: torch.device) -> dict[str, object]:
    """TAPTRv3's exported graphs through onnxruntime's GPU providers (`onnx_gpu_cases`)."""
    from onnx_gpu_cases import onnx_cases  # beside this script: imported when run

    from taptr.config import get_config

    torch.manual_seed(0)
    model = build_model(get_config(args.preset).replace(input_size=tuple(args.size))).eval()
    return onnx_cases(model, args.points, runs=max(3, args.frames // 2), float32=args.onnx_export)


CASES = {
    "taptrv3": v3_cases,
    "taptrv3_predictor": v3_predictor,
    "online_taptrv3": online_latency,
    "taptrv2_predictor": v2_predictor,
    "onnx_taptrv3": onnx_taptrv3,
}
"""Each case of the report, by its key; ``--cases`` picks some."""


def main(argv: list[str] | None = None) -> int:
    """Runs every case and prints one JSON object."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--preset", default="taptrv3")
    parser.add_argument("--size", type=int, nargs=2, default=(384, 512))
    parser.add_argument("--points", type=int, default=800)
    parser.add_argument("--frames", type=int, default=48)
    parser.add_argument("--v2-preset", default="taptrv2")
    parser.add_argument("--v2-size", type=int, nargs=2, default=(512, 512))
    parser.add_argument("--v2-points", type=int, nargs="+", default=[800, 5000])
    parser.add_argument(
        "--backend", default="inductor", help="torch.compile backend (eager: a quick CPU check)"
    )
    parser.add_argument(
        "--cases", nargs="+", default=list(CASES), help="cases to run (default: all)"
    )
    parser.add_argument("--onnx-export", default=None, help="a float32 TAPTRv3 export of --preset")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.cases) - set(CASES))
    if unknown:
        parser.error(f"unknown cases {unknown}; choose from {', '.join(CASES)}")
    device = torch.device(args.device)
    step_capture.BACKEND = args.backend
    report = {
        "machine": machine(),
        "command": " ".join(["python", "benchmarks/gpu_lean_step.py", *(argv or sys.argv[1:])]),
        **{name: run(args, device) for name, run in CASES.items() if name in args.cases},
    }
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
