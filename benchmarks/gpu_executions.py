"""Which parts of the CPU-tuned ``fast`` execution pay on this device, in one process.

The ``fast`` execution was tuned on CPUs (row and encoder blocks sized for caches, the
gather kernel, channels-last frames, frames encoded per window). On a GPU some of that
costs: this script times variants of it on the same weights and video, alternating, each
after one untimed warm-up and without ``taptr bench``'s per-stage synchronisation, and
prints seconds per frame, frames per second and the largest position change against
``fast``. ``--frames-up-front`` also runs every variant with all frames encoded in one batch
before tracking (what the ``reference`` execution of ``taptr bench`` does), so that the
batching and the execution's own choices can be told apart.

``python benchmarks/gpu_executions.py --device cuda``
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import torch

from taptr.apps.benchmark import BenchConfig, _inputs, _precision, _track, machine
from taptr.model.build import build_model
from taptr.model.execution import EXECUTIONS, Execution


def variants() -> dict[str, Execution]:
    """The executions compared, by name: ``fast`` and ``reference`` with one part swapped.

    Row blocks and oneDNN products are CPU-only already (`taptr.model.ops.row_blocks`,
    `taptr.model.ops.dense`), so the parts left to tell apart on a GPU are the kernel
    (with the shared frame tables it enables), the point attention's form and the
    backbone's memory layout.
    """
    fast, reference = EXECUTIONS["fast"], EXECUTIONS["reference"]
    return {
        "fast": fast,
        "fast, grid_sample kernel": dataclasses.replace(
            fast, kernel="grid_sample", shared_tables=False
        ),
        "fast, N x N point attention": dataclasses.replace(fast, grouped_point_attention=False),
        "fast, plain layout": dataclasses.replace(fast, channels_last=False, in_place_norms=False),
        "reference, gather kernel": dataclasses.replace(reference, kernel="gather"),
        "reference, grouped point attention": dataclasses.replace(
            reference, grouped_point_attention=True
        ),
        "reference": reference,
    }


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def main(argv: list[str] | None = None) -> int:
    """Times every variant (and, if asked, with frames up front); prints and writes a table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="taptrv2")
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--points", type=int, default=800)
    parser.add_argument("--size", type=int, nargs="+", help="H [W]: the frame size (square if one)")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--frames-up-front", action="store_true")
    parser.add_argument("--variants", nargs="+", help="names of the variants to run (default all)")
    parser.add_argument("--frames-per-call", type=int, nargs="+", default=[1],
                        help="frames per encoder call, per-window runs")  # fmt: skip
    parser.add_argument("--dtype", default="float32", choices=("float32", "bfloat16", "float16"),
                        help="autocast type the tracking runs under (float32: none)")  # fmt: skip
    parser.add_argument("--json", help="write the results to this file")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    size = (args.size * 2)[:2] if args.size else build_model(args.preset).config.input_size
    base = BenchConfig(args.preset, args.frames, args.points, tuple(size), device=args.device)
    video, queries = _inputs(base)
    weights = build_model(args.preset).state_dict()
    runs = []
    for name, execution in variants().items():
        if args.variants and name not in args.variants:
            continue
        model = build_model(args.preset, execution=execution).eval().to(args.device)
        model.load_state_dict(weights)
        # _track encodes every frame up front when its config says "reference"
        modes = ["up front", "per window"] if args.frames_up_front else [None]
        for mode in modes:
            up_front = execution.name == "reference" if mode is None else mode == "up front"
            config = dataclasses.replace(base, execution="reference" if up_front else "fast")
            for per_call in [0] if up_front else args.frames_per_call:
                where = "frames up front" if up_front else f"per window, {per_call} per call"
                runs.append((f"{name} ({where})", model, config, per_call))
    outputs, seconds = {}, {run[0]: [] for run in runs}
    precision = _precision(dataclasses.replace(base, dtype=args.dtype))
    with torch.no_grad(), precision:
        for label, model, config, per_call in runs:  # warm-up, and the outputs compared
            track = _track(model, config, video, queries, frames_per_call=max(per_call, 1))
            outputs[label] = track.positions.float()
            print(f"warmed up: {label}", flush=True)
        for _ in range(args.repeats):
            for label, model, config, per_call in runs:
                _sync(args.device)
                start = time.perf_counter()
                _track(model, config, video, queries, frames_per_call=max(per_call, 1))
                _sync(args.device)
                seconds[label].append((time.perf_counter() - start) / args.frames)
    first = runs[0][0]
    rows = []
    for label, *_ in runs:
        best = min(seconds[label])
        change = float((outputs[label] - outputs[first]).abs().max())
        rows.append({"execution": label, "seconds_per_frame": best, "max_position_change": change})
        print(f"{label:58s} {best:8.4f} s/frame {1 / best:7.1f} FPS  max |Δ position| {change:.1e}")
    if args.json:
        with open(args.json, "w") as file:
            json.dump({"args": vars(args), "machine": machine(), "rows": rows}, file, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
