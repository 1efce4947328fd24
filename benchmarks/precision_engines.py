"""Precisions side by side: PyTorch float32 and bfloat16, each engine × precision, one command.

Cases (``--cases``): ``torch_float32`` (``Predictor.track``, capture off: the baseline),
``torch_bfloat16`` (the predictor with bfloat16 autocast), and the torch-free
``OnnxTracker.track`` in ``openvino_float32``, ``openvino_bfloat16``, ``openvino_int8``,
``onnxruntime_float32``, ``onnxruntime_int8`` (`taptr.onnx.precisions`).

- **Speed** on TAPTRv3-R18 (``--preset``) at 384 × 512, ``--frames`` frames, each point
  count: untrained seeded weights (they set the work, not the tracks). Each case runs
  once on 2 frames untimed (compilation, first shapes), then ``--turns`` timed runs; the
  best is kept. The exported cases also report each graph's seconds per frame (encode,
  start_points, decode_step) and the encoder's achieved GOP/s from ``--encoder-gflop``.
- **Accuracy** on a trained model (``--checkpoint``, default the small TAPTRv3 trained
  here; it is smaller than R18, so accuracy and speed come from different models) on
  ``--videos`` videos of the photo benchmark (`taptr.data.photo_bench`, held-out
  photographs, 256 × 256, 24 frames): AJ, δ_avg and OA against the ground truth, and
  against ``torch_float32``: median and 99th-percentile pixel difference of the tracks
  and visibility agreement.

Prints one JSON object.

    python benchmarks/precision_engines.py --export r18_export/      # R18 export reused
    python benchmarks/precision_engines.py --preset tiny-v3 --size 48 64 --frames 4 \\
        --points 8 --videos 1 --checkpoint none                        # a quick check
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from taptr.api.predictor import Predictor
from taptr.apps.benchmark import machine
from taptr.eval.metrics import tapvid_metrics
from taptr.export.v3_graphs import export_v3
from taptr.onnx.graph_engines import StepGraphs, open_graphs
from taptr.onnx.video_tracker import OnnxTracker

CASES = (
    "torch_float32",
    "torch_bfloat16",
    "openvino_float32",
    "openvino_bfloat16",
    "openvino_int8",
    "onnxruntime_float32",
    "onnxruntime_int8",
)
"""Every case, the baseline first."""

Run = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
"""A tracker: video (T, H, W, 3) uint8, queries (N, 3) → tracks (T, N, 2), visible (T, N)."""


class TimedGraphs:
    """An engine's graphs with each graph's seconds added up (the engine's own calls)."""

    def __init__(self, graphs: StepGraphs) -> None:
        self.graphs = graphs
        self.manifest = graphs.manifest
        self.seconds = {"encode": 0.0, "start_points": 0.0, "decode_step": 0.0}

    def _timed(self, name: str, *args: Any) -> Any:
        start = time.perf_counter()
        out = getattr(self.graphs, name)(*args)
        self.seconds[name] += time.perf_counter() - start
        return out

    def encode(self, frames):
        return self._timed("encode", frames)

    def start_points(self, memory, positions):
        return self._timed("start_points", memory, positions)

    def decode_step(self, inputs):
        return self._timed("decode_step", inputs)


def trackers(model, folder: str, cases: list[str], threads: int) -> dict[str, Any]:
    """Each case's tracker: a `Predictor` or an `OnnxTracker` over `TimedGraphs`."""
    made: dict[str, Any] = {}
    for case in cases:
        engine, precision = case.split("_")
        if engine == "torch":
            autocast = torch.bfloat16 if precision == "bfloat16" else None
            made[case] = Predictor(model, device="cpu", capture="off", autocast=autocast)
        else:
            graphs = open_graphs(folder, engine, threads=threads, precision=precision)
            made[case] = OnnxTracker(graphs=TimedGraphs(graphs))
    return made


def run_of(tracker: Any) -> Run:
    """The tracker as a `Run`."""
    if isinstance(tracker, Predictor):

        def run(video, queries):
            result = tracker.track(video, queries)
            return result.tracks[0].numpy(), result.visibility[0].numpy()

        return run
    return lambda video, queries: (
        (result := tracker.track(video, queries)).tracks,
        result.visibility,
    )


def speed(args, made: dict[str, Any], points: int) -> dict[str, Any]:
    """Seconds per frame of each case at ``points`` points, graphs' shares, ratios."""
    height, width = args.size
    rng = np.random.default_rng(points)
    video = rng.integers(0, 256, (args.frames, height, width, 3), np.uint8)
    xy = rng.uniform(0.05, 0.95, (points, 2)) * [width - 1, height - 1]
    queries = np.concatenate([np.zeros((points, 1)), xy], 1).astype(np.float32)
    report: dict[str, Any] = {}
    for case, tracker in made.items():
        run = run_of(tracker)
        run(video[:2], queries)  # compilation and first shapes, untimed
        best, graphs = float("inf"), None
        for _ in range(args.turns):
            timed = getattr(tracker, "graphs", None)
            if isinstance(timed, TimedGraphs):
                timed.seconds = dict.fromkeys(timed.seconds, 0.0)
            start = time.perf_counter()
            run(video, queries)
            seconds = time.perf_counter() - start
            if seconds < best:
                best = seconds
                graphs = dict(timed.seconds) if isinstance(timed, TimedGraphs) else None
        entry: dict[str, Any] = {"seconds_per_frame": best / args.frames}
        if graphs is not None:
            per_frame = {name: s / args.frames for name, s in graphs.items()}
            entry["graph_seconds_per_frame"] = per_frame
            entry["encoder_gop_per_second"] = args.encoder_gflop / per_frame["encode"]
        report[case] = entry
        print(f"{points} points {case}: {entry}", file=sys.stderr)
    base = report.get("torch_float32", {}).get("seconds_per_frame")
    for entry in report.values():
        entry["speed_vs_torch_float32"] = base / entry["seconds_per_frame"] if base else None
    return report


def photo_videos(count: int, seed: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``count`` photo-benchmark videos: (video, tracks (T, N, 2), visible (T, N))."""
    from taptr.data.photo_bench import PhotoBenchConfig, make_photo_video
    from taptr.data.photos import load_builtin_photos

    photos = load_builtin_photos("heldout")
    config = PhotoBenchConfig()
    videos = []
    for index in range(count):
        sample = make_photo_video(np.random.default_rng((seed, index)), photos, config)
        videos.append((sample.video, sample.tracks, sample.visible))
    return videos


def first_queries(tracks: np.ndarray, visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """TAP-Vid's "first" queries (N', 3) of the points ever visible, and which points."""
    seen = visible.any(0)
    first = visible.argmax(0)[seen]
    xy = tracks[first, np.flatnonzero(seen)]
    return np.concatenate([first[:, None], xy], 1).astype(np.float32), seen


def accuracy(args, made: dict[str, Any]) -> dict[str, Any]:
    """Each case's photo-benchmark scores and its difference from ``torch_float32``."""
    per_case: dict[str, dict[str, list]] = {case: {} for case in made}
    for video, tracks, visible in photo_videos(args.videos, args.seed):
        queries, seen = first_queries(tracks, visible)
        tracks, visible = tracks[:, seen], visible[:, seen]
        outputs = {case: run_of(tracker)(video, queries) for case, tracker in made.items()}
        scored = np.arange(len(video))[:, None] >= queries[None, :, 0]  # from each query on
        base_tracks, base_visible = outputs.get("torch_float32", (None, None))
        for case, (got_tracks, got_visible) in outputs.items():
            found = per_case[case]
            metrics = tapvid_metrics(queries, tracks, visible, got_tracks, got_visible, "first")
            for key in ("average_jaccard", "average_pts_within_thresh", "occlusion_accuracy"):
                found.setdefault(key, []).append(metrics[key])
            if base_tracks is not None:
                distance = np.linalg.norm(got_tracks - base_tracks, axis=-1)[scored]
                found.setdefault("distances", []).append(distance)
                agree = (got_visible == base_visible)[scored]
                found.setdefault("agreement", []).append(agree)
    report = {}
    for case, found in per_case.items():
        entry = {
            "AJ": 100 * float(np.mean(found["average_jaccard"])),
            "delta_avg": 100 * float(np.mean(found["average_pts_within_thresh"])),
            "OA": 100 * float(np.mean(found["occlusion_accuracy"])),
        }
        if "distances" in found:
            distances = np.concatenate(found["distances"])
            entry["median_px_vs_torch_float32"] = float(np.median(distances))
            entry["p99_px_vs_torch_float32"] = float(np.percentile(distances, 99))
            entry["visibility_agreement"] = float(np.concatenate(found["agreement"]).mean())
        report[case] = entry
        print(f"accuracy {case}: {entry}", file=sys.stderr)
    return report


def seeded_model(preset: str, size: tuple[int, int]) -> torch.nn.Module:
    """The preset at the benchmark's input size, seeded (untrained)."""
    from taptr.config import get_config
    from taptr.model.build import build_model

    torch.manual_seed(0)
    return build_model(get_config(preset).replace(input_size=tuple(size))).eval()


def exported(model, folder: str | None, scratch: str, name: str) -> str:
    """``folder`` (an export of the same model, made there when missing), else a fresh one."""
    target = folder if folder is not None else str(Path(scratch) / name)
    if not (Path(target) / "taptr-export.json").is_file():
        export_v3(model, target)
    return target


def main(argv: list[str] | None = None) -> int:
    """Runs the speed and accuracy cases and prints one JSON object."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="taptrv3")
    parser.add_argument("--size", type=int, nargs=2, default=(384, 512))
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--points", type=int, nargs="*", default=[100, 800])
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--turns", type=int, default=1)
    parser.add_argument(
        "--export",
        default=None,
        help="an export folder of the seeded preset (made there when missing)",
    )
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    parser.add_argument(
        "--encoder-gflop",
        type=float,
        default=83.0,
        help="the encoder's GFLOP per frame (R18 at 384 x 512: taptr bench --flops)",
    )
    parser.add_argument(
        "--checkpoint",
        default="/work/models/small_v3_warm.pt",
        help="the trained TAPTRv3 scored on the photo benchmark ('none': no accuracy)",
    )
    parser.add_argument(
        "--accuracy-export",
        default=None,
        help="an export of --checkpoint (made there when missing)",
    )
    parser.add_argument("--videos", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    report: dict[str, Any] = {
        "machine": machine(),
        "onnxruntime": __import__("onnxruntime").__version__,
        "openvino": __import__("openvino").__version__,
        "command": " ".join(["python", "benchmarks/precision_engines.py", *(argv or sys.argv[1:])]),
        "threads": args.threads,
    }
    with tempfile.TemporaryDirectory(prefix="taptr-precision-") as scratch:
        if args.points:
            model = seeded_model(args.preset, args.size)
            folder = exported(model, args.export, scratch, "speed")
            made = trackers(model, folder, args.cases, args.threads)
            report["speed"] = {str(p): speed(args, made, p) for p in args.points}
            del made
        if args.checkpoint != "none":
            from taptr.weights.checkpoint import load_checkpoint

            trained = load_checkpoint(args.checkpoint).eval()
            folder = exported(trained, args.accuracy_export, scratch, "accuracy")
            report["accuracy_model"] = {
                "checkpoint": args.checkpoint,
                "input_size": list(trained.config.input_size),
            }
            report["accuracy"] = accuracy(args, trackers(trained, folder, args.cases, args.threads))
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
