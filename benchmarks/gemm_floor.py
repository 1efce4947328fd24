"""How close the fast execution is to its matrix-product floor on this machine.

Nearly all of the tracker's FLOPs are matrix products and convolutions, so the time they
would take at the machine's matrix-product rate is a floor on the whole run. This script
measures, in one process: the best-of-five rate of one 2048³ product (what ``taptr bench``
calls the peak: the faster of the BLAS and oneDNN), the rates sustained over ten seconds by
the products the paper model runs most (its encoder FFN's 2,048-row blocks, its 256 × 256
projections) through the BLAS (``F.linear``) and through oneDNN (`taptr.model.ops.dense`),
the tracker's FLOPs per frame (``torch.utils.flop_counter``), and the tracker's own time
per frame. It prints the floor (FLOPs at the faster sustained rate) next to the measured
time.

``python benchmarks/gemm_floor.py --threads 2``
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
from torch.nn.attention import SDPBackend, sdpa_kernel
from torch.utils.flop_counter import FlopCounterMode

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fast_execution_parts import _tracker

from taptr.apps.benchmark import peak_flops
from taptr.model.build import build_model
from taptr.model.ops.dense import linear

SHAPES = ((2048, 256, 2048), (2048, 2048, 256), (4096, 256, 256))
"""(rows, in, out) of the products timed for the sustained rate."""


def sustained_rate(seconds: float, onednn: bool) -> float:
    """FLOP/s of `SHAPES` run in turn for ``seconds``, through oneDNN or the BLAS."""
    generator = torch.Generator().manual_seed(0)
    cases = [
        (torch.randn(m, k, generator=generator), torch.randn(n, k, generator=generator))
        for m, k, n in SHAPES
    ]
    flops = 0
    start = time.perf_counter()
    while time.perf_counter() - start < seconds:
        for x, w in cases:
            linear(x, w, None, onednn=onednn)
            flops += 2 * x.shape[0] * x.shape[1] * w.shape[0]
    return flops / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--preset", default="taptrv2", help="model preset (default taptrv2)")
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--points", type=int, default=800)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--seconds", type=float, default=10.0, help="sustained-rate run")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = build_model(args.preset, execution="fast").eval()
    track = _tracker(model, torch.Generator().manual_seed(0), args.frames, args.size, args.points)
    with torch.no_grad():
        track()  # warm-up
        start = time.perf_counter()
        track()
        seconds_per_frame = (time.perf_counter() - start) / args.frames
        counter = FlopCounterMode(display=False)
        with sdpa_kernel(SDPBackend.MATH), counter:
            track()
    flops_per_frame = counter.get_total_flops() / args.frames
    peak = peak_flops(args.threads)
    with torch.no_grad():
        rates = {
            name: sustained_rate(args.seconds, name == "onednn") for name in ("blas", "onednn")
        }
    sustained = max(rates.values())
    results = {
        "threads": args.threads,
        "seconds_per_frame": seconds_per_frame,
        "gflop_per_frame": flops_per_frame / 1e9,
        "peak_gflops": peak / 1e9,
        "sustained_gflops": sustained / 1e9,
        "sustained_gflops_blas": rates["blas"] / 1e9,
        "sustained_gflops_onednn": rates["onednn"] / 1e9,
        "floor_at_peak_s": flops_per_frame / peak,
        "floor_at_sustained_s": flops_per_frame / sustained,
    }
    print(f"tracker {seconds_per_frame:.3f} s/frame, {flops_per_frame / 1e9:.1f} GFLOP/frame")
    print(", ".join(f"{name} sustained {rate / 1e9:.0f} GFLOP/s" for name, rate in rates.items()))
    for name, rate, floor in (
        ("peak (best of five 2048^3)", peak, results["floor_at_peak_s"]),
        (
            f"sustained ({args.seconds:.0f} s, the model's shapes, the faster path)",
            sustained,
            results["floor_at_sustained_s"],
        ),
    ):
        share = floor / seconds_per_frame
        print(
            f"{name}: {rate / 1e9:.0f} GFLOP/s, floor {floor:.3f} s/frame ({share:.0%} of the run)"
        )
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
