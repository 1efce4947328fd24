"""What each part of the fast execution buys, measured in paired runs on a noisy machine.

Every part is a field of `taptr.model.execution.Execution`, so switching it off is the fast
execution with one field changed; the outputs of both are compared too. Each repetition
runs the part off and on back to back (the order alternating between repetitions), and the
result is the median of the per-pair ratios: a shared host whose matrix-product speed drifts
by ±20% within seconds moves both runs of a pair alike, which a ratio of two separate
medians does not cancel.

Cases (by default the paper preset, random weights, 512 × 512 frames, 800 points):

- ``channels_last``, ``in_place_norms``: backbone and input projections on one frame;
- ``encoder_block``: the deformable encoder on one frame's feature maps;
- ``onednn_linear (encoder)``: the same encoder, linear layers through oneDNN or BLAS;
- ``shared_tables``: the whole tracker on a random video (the tables are shared across
  windows);
- ``onednn_linear``: the whole tracker, every linear layer through oneDNN or BLAS;
- ``all``: the whole tracker on a random video, every part above off against on.

With ``--processes``, only the whole tracker, every run in a fresh process (what ``taptr
bench`` does), every part off against on, or with ``--part NAME`` that part alone. With
``--row-block N``, the cases are the encoder, the decoder window and the whole tracker,
and "off" is the fast execution with MLP row blocks of N rows instead of its own.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from taptr.model.build import build_model
from taptr.model.execution import Execution, get_execution
from taptr.model.sliding_window import run_windows
from taptr.model.taptr import TAPTR, normalize_frames
from taptr.model.trajectory import QuerySet
from taptr.runtime.frames import EncodedFrames

PARTS_OFF = {
    "encoder_block": None,
    "shared_tables": False,
    "channels_last": False,
    "in_place_norms": False,
    "onednn_linear": False,
}


def _timed(run: Callable[[], torch.Tensor]) -> tuple[float, torch.Tensor]:
    start = time.perf_counter()
    out = run()
    return time.perf_counter() - start, out


def paired(
    model: TAPTR, off: Execution, on: Execution, run: Callable[[], torch.Tensor], repeats: int
) -> dict[str, Any]:
    """Runs ``run`` under both executions ``repeats`` times each, in alternating pairs."""
    times: dict[str, list[float]] = {"off": [], "on": []}
    outputs: dict[str, torch.Tensor] = {}
    model.set_execution(on)
    run()  # warm-up: first-call allocations and oneDNN primitive creation
    for index in range(repeats):
        order = [("off", off), ("on", on)]
        for name, execution in order if index % 2 == 0 else order[::-1]:
            model.set_execution(execution)
            seconds, outputs[name] = _timed(run)
            times[name].append(seconds)
    summary = _summary(times)
    summary["max_abs_difference"] = float((outputs["off"] - outputs["on"]).abs().max())
    return summary


def _summary(times: dict[str, list[float]]) -> dict[str, Any]:
    ratios = sorted(a / b for a, b in zip(times["off"], times["on"], strict=True))
    quarter = len(ratios) // 4
    return {
        "off_median_s": statistics.median(times["off"]),
        "on_median_s": statistics.median(times["on"]),
        "speedup_median": statistics.median(ratios),
        "speedup_quartiles": [ratios[quarter], ratios[-1 - quarter]],
    }


def isolated(arguments: list[str], repeats: int) -> dict[str, Any]:
    """The ``all`` case with every run in a fresh process (pairs alternating in order)."""
    times: dict[str, list[float]] = {"off": [], "on": []}
    for index in range(repeats):
        for part in ("off", "on") if index % 2 == 0 else ("on", "off"):
            command = [sys.executable, __file__, *arguments, "--run-once", part]
            done = subprocess.run(command, capture_output=True, text=True, check=True)
            times[part].append(float(done.stdout.split()[-1]))
    return _summary(times)


def cases(
    model: TAPTR, repeats: int, frames: int, size: int, points: int
) -> dict[str, dict[str, Any]]:
    """The cases of the module docstring, on ``size`` × ``size`` frames."""
    fast = get_execution("fast")
    generator = torch.Generator().manual_seed(0)
    image = torch.randn(1, 3, size, size, generator=generator)
    results = {}
    with torch.no_grad():
        for part in ("channels_last", "in_place_norms"):
            off = dataclasses.replace(fast, **{part: False})
            results[part] = paired(model, off, fast, lambda: model.feature_maps(image)[0], repeats)
        maps = model.input_projections(model.backbone(image))
        encoder_cases = {"encoder_block": {"encoder_block": None}}
        encoder_cases["onednn_linear (encoder)"] = {"onednn_linear": False}
        for name, changes in encoder_cases.items():
            off = dataclasses.replace(fast, **changes)
            results[name] = paired(
                model, off, fast, lambda: model.encoder(maps, model.execution), repeats
            )
        # tables are shared across windows, so this part is timed on the whole tracker
        tracker_cases = {
            "shared_tables": {"shared_tables": False},
            "onednn_linear": {"onednn_linear": False},
            "all": PARTS_OFF,
        }
        for name, changes in tracker_cases.items():
            results[name] = paired(
                model,
                dataclasses.replace(fast, **changes),
                fast,
                _tracker(model, generator, frames, size, points),
                max(1, repeats // 3),
            )
    return results


def row_block_cases(
    model: TAPTR, repeats: int, frames: int, size: int, points: int, rows: int
) -> dict[str, dict[str, Any]]:
    """The fast execution with MLP row blocks of ``rows`` (off) against its own (on)."""
    fast = get_execution("fast")
    off = dataclasses.replace(fast, row_block=rows)
    generator = torch.Generator().manual_seed(0)
    image = torch.randn(1, 3, size, size, generator=generator)
    with torch.no_grad():
        maps = model.input_projections(model.backbone(image))
        runs = {
            "encoder": (lambda: model.encoder(maps, model.execution), repeats),
            "decoder": (_decoder_window(model, generator, size, points), repeats),
            "all": (_tracker(model, generator, frames, size, points), max(1, repeats // 3)),
        }
        return {
            f"{name} (row blocks {rows} -> {fast.row_block})": paired(model, off, fast, run, count)
            for name, (run, count) in runs.items()
        }


def _decoder_window(
    model: TAPTR, generator: torch.Generator, size: int, points: int
) -> Callable[[], torch.Tensor]:
    features = model.encode_images(torch.randn(1, 3, size, size, generator=generator))
    window = model.window_size
    memory = features.memory[:, None].expand(1, window, -1, -1).contiguous()  # (1, W_t, S, C)
    channels = memory.shape[-1]
    content = torch.randn(1, window, points, channels, generator=generator)
    positions = torch.randn(1, window, points, 4, generator=generator)
    tracking = torch.ones(1, window, points, dtype=torch.bool)
    args = (memory, features.spatial_shapes, content, positions, tracking, tracking)
    return lambda: model.decode_window(*args).positions


def _tracker(
    model: TAPTR, generator: torch.Generator, frames: int, size: int, points: int
) -> Callable[[], torch.Tensor]:
    shape = (1, frames, 3, size, size)
    video = torch.randint(0, 256, shape, generator=generator, dtype=torch.uint8)
    queries = QuerySet(
        torch.zeros(1, points, dtype=torch.long),
        torch.rand(1, points, 2, generator=generator) * 0.9 + 0.05,
        torch.ones(1, points, dtype=torch.bool),
    )

    def load(first: int, last: int) -> torch.Tensor:
        return normalize_frames(video[:, first : last + 1].float() / 255)

    def track() -> torch.Tensor:
        return run_windows(
            model, queries, frames, EncodedFrames(model, load), torch.float32
        ).positions

    return track


def sizes(args: argparse.Namespace) -> tuple[int, int, int]:
    """(frames, size, points) of the command line."""
    return args.frames, args.size, args.points


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=9, help="pairs per case (default 9)")
    parser.add_argument("--frames", type=int, default=12, help="video length of 'all'")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--preset", default="taptrv2", help="model preset (default taptrv2)")
    parser.add_argument("--size", type=int, default=512, help="frame side (default 512)")
    parser.add_argument("--points", type=int, default=800, help="query points (default 800)")
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument(
        "--processes",
        action="store_true",
        help="only the whole tracker, each run in its own process (--repeats pairs)",
    )
    parser.add_argument(
        "--part",
        choices=sorted(PARTS_OFF),
        help="with --processes: only this part off against on (default: all of them)",
    )
    parser.add_argument(
        "--row-block",
        type=int,
        metavar="N",
        help="compare MLP row blocks of N rows (off) with the fast execution's own (on)",
    )
    parser.add_argument("--run-once", choices=("off", "on"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = build_model(args.preset, execution="fast").eval()
    if args.run_once:
        parts_off = {args.part: PARTS_OFF[args.part]} if args.part else PARTS_OFF
        off = dataclasses.replace(model.execution, **parts_off)
        model.set_execution(off if args.run_once == "off" else model.execution)
        track = _tracker(model, torch.Generator().manual_seed(0), *sizes(args))
        with torch.no_grad():
            print(_timed(track)[0])
        return
    if args.processes:
        common = ["--threads", str(args.threads), "--preset", args.preset]
        for flag, value in zip(("--frames", "--size", "--points"), sizes(args), strict=True):
            common += [flag, str(value)]
        if args.part:
            common += ["--part", args.part]
        name = f"{args.part or 'all'} (separate processes)"
        results = {name: isolated(common, args.repeats)}
    elif args.row_block:
        results = row_block_cases(model, args.repeats, *sizes(args), args.row_block)
    else:
        results = cases(model, args.repeats, *sizes(args))
    for name, result in results.items():
        low, high = result["speedup_quartiles"]
        print(
            f"{name:30} off {result['off_median_s']:.3f} s  on {result['on_median_s']:.3f} s  "
            f"speed-up {result['speedup_median']:.3f} (quartiles {low:.3f}-{high:.3f})"
            + (
                f"  max |diff| {result['max_abs_difference']:.2e}"
                if "max_abs_difference" in result
                else ""
            )
        )
    if args.json:
        args.json.write_text(json.dumps({"threads": args.threads, **results}, indent=2) + "\n")


if __name__ == "__main__":
    main()
