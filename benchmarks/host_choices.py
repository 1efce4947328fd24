"""What this machine measures for the speed-only choices the predictor makes, and why.

Times every candidate of each measured choice of `taptr.runtime.cpu_choice` (oneDNN or the
BLAS for the linear layers, channels-last frames or not) and `taptr.runtime.encode_choice`
(frames per encoder call) on the paper preset's random weights, at each input size asked,
and prints the timings next to what the predictor would choose. Nothing is remembered:
this measures afresh.

``python benchmarks/host_choices.py --sizes 128 256 512 [--dtype bfloat16] [--json FILE]``
"""

from __future__ import annotations

import argparse
import contextlib
import json

import torch

from taptr.apps.benchmark import machine
from taptr.model.build import build_model
from taptr.model.execution import CHANNELS_LAST_MIN_PIXELS
from taptr.model.ops.dense import bfloat16_products
from taptr.runtime.cpu_choice import time_layouts, time_products
from taptr.runtime.encode_choice import candidates, fastest, time_frames_per_call
from taptr.runtime.measured import TOLERANCE


def main(argv: list[str] | None = None) -> int:
    """Prints (and writes, if asked) the timings of every candidate."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="taptrv2")
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32")
    parser.add_argument("--json", help="write the results to this file")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = build_model(args.preset).eval()
    bfloat16 = args.dtype == "bfloat16"
    if bfloat16:
        model.bfloat16_trunk()
    results: dict[str, object] = {"machine": machine(), "args": vars(args)}
    cpu = torch.device("cpu")
    with torch.no_grad(), bfloat16_products() if bfloat16 else contextlib.nullcontext():
        if not bfloat16:
            products = time_products(model)
            results["products"] = products
            print(f"encoder FFN, 4096 rows: oneDNN {products[True] * 1e3:.1f} ms, "
                  f"BLAS {products[False] * 1e3:.1f} ms")  # fmt: skip
        for size in args.sizes:
            shape = (size, size)
            row: dict[str, object] = {}
            if size * size >= CHANNELS_LAST_MIN_PIXELS:
                layouts = time_layouts(model, shape)
                row["layouts"] = layouts
                print(f"{size}x{size} backbone: channels-last {layouts[True] * 1e3:.1f} ms, "
                      f"plain {layouts[False] * 1e3:.1f} ms")  # fmt: skip
            sizes = candidates(cpu, shape)
            if len(sizes) > 1:
                seconds = time_frames_per_call(model, cpu, shape, sizes)
                row["frames_per_call"] = {"seconds_per_frame": seconds, "chosen": fastest(seconds)}
                timings = ", ".join(f"{n}: {s * 1e3:.1f}" for n, s in seconds.items())
                print(f"{size}x{size} encoder ms/frame by frames per call: {timings} "
                      f"-> {fastest(seconds)} (tolerance {TOLERANCE:.0%})")  # fmt: skip
            results[f"{size}x{size}"] = row
    if args.json:
        with open(args.json, "w") as file:
            json.dump(results, file, indent=1, default=str)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
