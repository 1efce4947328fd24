"""TAPTRv3 exported to ONNX against PyTorch on this CPU, side by side in one process.

Per point count, in float32, with PyTorch and each engine (``--engines``: onnxruntime and
OpenVINO, `taptr.onnx.graph_engines`) on the same threads:

- the per-frame decoder step, frames encoded beforehand (the same memory for all):
  PyTorch eager (the predictor's step), PyTorch captured (Inductor, compiled once before
  timing: `taptr.runtime.step_capture`), and the exported ``decode_step`` driven by the
  torch-free loop (`taptr.onnx.frame_loop`) in each engine (``step_onnx`` is
  onnxruntime's, ``step_openvino`` OpenVINO's);
- whole videos, encoding included: ``Predictor.track`` (capture off, which is what
  ``auto`` picks for a 24-frame video here) against the torch-free ``OnnxTracker.track``
  in each engine (``onnx_track``, ``openvino_track``), all with the model's support
  points.

Cases run in turns (one of each, then again) and the best of the turns is kept: on a
shared machine only times measured together compare. Weights are the architecture's,
untrained (seeded): they set the work, not the tracks. Prints one JSON object.

    python benchmarks/onnx_v3_cpu.py                       # TAPTRv3-R18, 384 × 512, 24 frames
    python benchmarks/onnx_v3_cpu.py --engines openvino      # one engine
    python benchmarks/onnx_v3_cpu.py --preset tiny-v3 --size 48 64 --frames 6 --points 8 \\
        --turns 1 --backend eager                         # a quick check of the script
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Callable
from importlib.util import find_spec
from typing import Any

import numpy as np
import torch

from taptr.api.predictor import Predictor
from taptr.apps.benchmark import machine
from taptr.export.v3_graphs import export_v3
from taptr.model.build import build_model
from taptr.model.taptr import normalize_frames
from taptr.model.trajectory import QuerySet
from taptr.model.v3.per_frame import run_frames
from taptr.onnx.frame_loop import add_points, decode_frame, start_state
from taptr.onnx.graph_engines import StepGraphs, open_graphs
from taptr.onnx.video_tracker import OnnxTracker
from taptr.runtime import step_capture
from taptr.runtime.frames import PrecomputedFrames
from taptr.runtime.step_capture import StepCapture


def step_torch(model, memory, xy, capture: str) -> tuple[Callable[[], Any], str]:
    """PyTorch's per-frame step over encoded frames, eager or captured; positions (T, N, 2)."""
    points, frames = len(xy), memory.memory.shape[1]
    queries = QuerySet(
        torch.zeros(1, points, dtype=torch.long),
        torch.from_numpy(xy)[None],
        torch.ones(1, points, dtype=torch.bool),
    )

    def run() -> np.ndarray:
        step = StepCapture(model.decoder, torch.device("cpu"), capture, str, points, frames)
        with torch.no_grad():
            out = run_frames(
                model, queries, frames, PrecomputedFrames(memory), torch.float32, step=step
            )
        return out.positions[0].numpy()

    return run, f"step_{'captured' if capture == 'on' else 'eager'}"


def step_onnx(graphs: StepGraphs, memory: np.ndarray, xy: np.ndarray) -> Callable[[], Any]:
    """The exported step through the torch-free loop over the same memory; positions."""

    def run() -> np.ndarray:
        state = start_state(graphs.manifest)
        add_points(graphs.manifest, state, np.zeros(len(xy), np.int64), xy)
        results = [decode_frame(graphs, state, lambda f: memory[f]) for _ in memory]
        return np.stack([r.positions for r in results])

    return run


PREFIXES = {"onnxruntime": "onnx", "openvino": "openvino"}
"""How each engine's cases are named (onnxruntime's keep the names of earlier reports)."""


def whole_video(predictor: Predictor, trackers: dict, video, queries) -> dict[str, Any]:
    """``Predictor.track`` and each engine's ``OnnxTracker.track`` on one video; tracks."""
    cases = {"predictor_track": lambda: predictor.track(video, queries).tracks[0].numpy()}
    for engine, tracker in trackers.items():
        cases[f"{PREFIXES[engine]}_track"] = lambda tracker=tracker: (
            tracker.track(video, queries).tracks
        )
    return cases


def in_turns(cases: dict[str, Callable[[], Any]], turns: int) -> dict[str, Any]:
    """Each case once untimed, then ``turns`` rounds of one run each; best seconds, output."""
    outputs = {name: run() for name, run in cases.items()}
    best = dict.fromkeys(cases, float("inf"))
    for _ in range(turns):
        for name, run in cases.items():
            start = time.perf_counter()
            outputs[name] = run()
            best[name] = min(best[name], time.perf_counter() - start)
    return {"seconds": best, "outputs": outputs}


def one_count(args, model, engines, predictor, memory, video, points) -> dict:
    """Every case at one point count: seconds per frame, ratios, agreement on frame 1.

    ``engines``: engine name → (its graphs, its tracker).
    """
    height, width = args.size
    xy = np.random.default_rng(points).uniform(0.05, 0.95, (points, 2)).astype(np.float32)
    cases = {
        f"step_{PREFIXES[name]}": step_onnx(graphs, memory.memory[0].numpy(), xy)
        for name, (graphs, _) in engines.items()
    }
    for capture in ["off"] + ([] if args.skip_capture else ["on"]):
        run, name = step_torch(model, memory, xy, capture)
        cases[name] = run
    queries = np.concatenate([np.zeros((points, 1)), xy * [width - 1, height - 1]], 1)
    trackers = {name: tracker for name, (_, tracker) in engines.items()}
    cases.update(whole_video(predictor, trackers, video, queries.astype(np.float32)))
    measured = in_turns(cases, args.turns)
    per_frame = {name: s / args.frames for name, s in measured["seconds"].items()}
    out = measured["outputs"]
    report: dict[str, Any] = {"seconds_per_frame": per_frame}
    for name in engines:
        prefix = PREFIXES[name]
        step, track = f"step_{prefix}", f"{prefix}_track"
        report[f"{prefix}_step_speed_vs_eager"] = per_frame["step_eager"] / per_frame[step]
        report[f"{prefix}_track_time_vs_predictor"] = (
            per_frame[track] / per_frame["predictor_track"]
        )
        report[f"{prefix}_frame_1_max_position_difference"] = float(
            np.abs(out[step][1] - out["step_eager"][1]).max()
        )
        report[f"{prefix}_track_frame_1_max_pixel_difference"] = float(
            np.abs(out[track][1] - out["predictor_track"][1]).max()
        )
    return report


def main(argv: list[str] | None = None) -> int:
    """Exports (or reads) the graphs, runs every case and prints one JSON object."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="taptrv3")
    parser.add_argument("--size", type=int, nargs=2, default=(384, 512))
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--points", type=int, nargs="+", default=[100, 800])
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--turns", type=int, default=2)
    parser.add_argument("--checkpoint", default=None, help="a TAPTRv3 checkpoint instead")
    parser.add_argument("--export", default=None, help="an export folder of the same model")
    parser.add_argument("--skip-capture", action="store_true", help="no captured step")
    parser.add_argument("--backend", default="inductor", help="the capture's compile backend")
    parser.add_argument(
        "--engines",
        nargs="+",
        default=["onnxruntime", "openvino"] if find_spec("openvino") else ["onnxruntime"],
        choices=list(PREFIXES),
        help="the engines that run the export (default: both where OpenVINO is installed)",
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    step_capture.BACKEND = args.backend
    model = load_model(args)
    with tempfile.TemporaryDirectory(prefix="taptr-onnx-v3-") as scratch:
        began = time.perf_counter()
        if args.export is None:
            export_v3(model, scratch)
        exported = time.perf_counter() - began
        folder = args.export or scratch
        results = run_cases(args, model, folder)
    report = {
        "machine": machine(),
        "onnxruntime": __import__("onnxruntime").__version__,
        "openvino": __import__("openvino").__version__ if "openvino" in args.engines else None,
        "command": " ".join(["python", "benchmarks/onnx_v3_cpu.py", *(argv or sys.argv[1:])]),
        "threads": args.threads,
        "export_seconds": exported if args.export is None else None,
        "points": results,
    }
    print(json.dumps(report, indent=1))
    return 0


def run_cases(args: argparse.Namespace, model: torch.nn.Module, folder: str) -> dict:
    """Every point count's cases over the export in ``folder``."""
    engines = {}
    for name in args.engines:
        graphs = open_graphs(folder, name, threads=args.threads)
        engines[name] = (graphs, OnnxTracker(graphs=graphs))
    predictor = Predictor(model, device="cpu", capture="off")
    video = np.random.default_rng(0).integers(0, 256, (args.frames, *args.size, 3), np.uint8)
    frames = torch.from_numpy(video).permute(0, 3, 1, 2).float() / 255
    with torch.no_grad():
        memory = model.encode(normalize_frames(frames)[None])
    return {
        str(points): one_count(args, model, engines, predictor, memory, video, points)
        for points in args.points
    }


def load_model(args: argparse.Namespace) -> torch.nn.Module:
    """``--checkpoint``, or the preset at the benchmark's input size, seeded."""
    from taptr.config import get_config
    from taptr.weights.checkpoint import load_checkpoint

    if args.checkpoint is not None:
        return load_checkpoint(args.checkpoint).eval()
    torch.manual_seed(0)
    return build_model(get_config(args.preset).replace(input_size=tuple(args.size))).eval()


if __name__ == "__main__":
    raise SystemExit(main())
