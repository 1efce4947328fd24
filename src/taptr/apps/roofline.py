"""How far each part of the model runs from this host's product rate (``taptr bench --flops``).

A part's work is counted as ``torch.utils.flop_counter`` counts it: the matrix products
and convolutions, 2 FLOPs per multiply-add (attention with the math backend, so that it
is counted; sampling, gathers, norms and other elementwise passes count zero). Its rate
is that count over its measured time, and its share is the rate over the host's peak
for the precision its products run in, measured here with one large product of each:
float32 (the faster of the BLAS and oneDNN, `taptr.apps.benchmark.peak_flops`),
bfloat16 (oneDNN inside `taptr.model.ops.dense.bfloat16_products`, on CPUs that multiply
bfloat16 natively) and int8 (``torch._int_mm``, where PyTorch has it on CPUs). A part far
below its share is spending its time on what the count leaves out.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor, nn

if TYPE_CHECKING:
    from torch.utils.flop_counter import FlopCounterMode

PRECISIONS = ("float32", "bfloat16", "int8")
"""The precisions whose peak `peak_rates` measures."""


def _best_rate(product: Callable[[], Tensor], size: int, repeats: int) -> float:
    """FLOP/s of the fastest of ``repeats`` runs of a ``size``³ product (after one untimed)."""
    product()
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        product()
        best = min(best, time.perf_counter() - start)
    return 2 * size**3 / best


def bfloat16_peak(size: int = 2048, repeats: int = 5) -> float | None:
    """bfloat16 products through oneDNN (FLOP/s), or None on a CPU without native bfloat16."""
    from taptr.model.ops.dense import bfloat16_products, linear, native_bfloat16

    if not native_bfloat16():
        return None
    a, weight = torch.randn(size, size), torch.randn(size, size)
    with bfloat16_products():
        x = a.to(torch.bfloat16)
        return _best_rate(lambda: linear(x, weight, None, onednn=True), size, repeats)


def int8_peak(size: int = 2048, repeats: int = 5) -> float | None:
    """int8 products with int32 sums by ``torch._int_mm`` (OP/s), or None without it."""
    product = getattr(torch, "_int_mm", None)
    if product is None:
        return None
    generator = torch.Generator().manual_seed(0)
    a = torch.randint(-128, 128, (size, size), dtype=torch.int8, generator=generator)
    b = torch.randint(-128, 128, (size, size), dtype=torch.int8, generator=generator)
    try:
        return _best_rate(lambda: product(a, b), size, repeats)
    except RuntimeError:  # builds without a CPU kernel for it
        return None


def peak_rates(threads: int) -> dict[str, float | None]:
    """This host's measured peak per precision on ``threads`` threads (None: not here)."""
    from taptr.apps.benchmark import peak_flops

    torch.set_num_threads(threads)
    return {"float32": peak_flops(threads), "bfloat16": bfloat16_peak(), "int8": int8_peak()}


@contextmanager
def stage_flops(
    model: nn.Module, stages: tuple[str, ...], counter: FlopCounterMode
) -> Iterator[dict[str, int]]:
    """Accumulates the FLOPs ``counter`` counts inside each of the model's top-level stages.

    The stages are submodules called one after another, never inside each other, so a
    stage's FLOPs are the counter's growth between entering and leaving it.
    """
    totals: dict[str, int] = defaultdict(int)
    entered: dict[str, int] = {}
    handles = []
    for name in stages:
        module = getattr(model, name)

        def before(*_: Any, name: str = name) -> None:
            entered[name] = counter.get_total_flops()

        def after(*_: Any, name: str = name) -> None:
            totals[name] += counter.get_total_flops() - entered[name]

        handles += [module.register_forward_pre_hook(before), module.register_forward_hook(after)]
    try:
        yield totals
    finally:
        for handle in handles:
            handle.remove()


def precision_of(config: dict[str, Any]) -> str:
    """The precision a bench case's products run in: bfloat16 or float16 where asked."""
    return "bfloat16" if config["dtype"] == "bfloat16" else "float32"


def roofline_rows(result: Any, peaks: dict[str, float | None]) -> list[dict[str, Any]]:
    """Per stage of one `taptr.apps.benchmark.BenchResult`: GFLOP, seconds and share, per frame.

    Returns:
        one dict per stage with FLOPs counted: ``stage``, ``gflop`` and ``seconds`` per
        frame, ``gflops`` (the rate), ``precision`` and ``share`` of that precision's
        peak (None where the peak is not known here).
    """
    config = result.config
    frames = config["frames"]
    precision = precision_of(config)
    peak = peaks.get(precision)
    rows = []
    for stage, flops in (result.extra.get("stage_flops") or {}).items():
        seconds = result.stage_seconds.get(stage, 0.0) / frames
        rate = flops / frames / seconds if seconds > 0 else 0.0
        rows.append(
            {
                "stage": stage,
                "gflop": flops / frames / 1e9,
                "seconds": seconds,
                "gflops": rate / 1e9,
                "precision": precision,
                "share": rate / peak if peak else None,
            }
        )
    return rows


def format_peaks(peaks: dict[str, float | None], threads: int) -> str:
    """One line: each precision's measured peak, or n/a."""
    shown = ", ".join(
        f"{name} {rate / 1e9:.0f}" if rate else f"{name} n/a" for name, rate in peaks.items()
    )
    return f"measured peak on {threads} threads (GFLOP/s; int8 in GOP/s): {shown}"


def format_roofline(results: list[Any], peaks: dict[str, float | None]) -> str:
    """The roofline table: each case's stages, GFLOP and seconds per frame, rate and share."""
    lines = [
        f"{'preset':10} {'execution':9} {'N':>6} {'stage':17} {'GFLOP':>8} {'s/frame':>8} "
        f"{'GFLOP/s':>8} {'share of peak':>14}"
    ]
    for result in results:
        config = result.config
        for row in roofline_rows(result, peaks):
            share = "n/a" if row["share"] is None else f"{row['share']:.0%} {row['precision']}"
            lines.append(
                f"{config['preset']:10} {config['execution']:9} {config['points']:6d} "
                f"{row['stage']:17} {row['gflop']:8.2f} {row['seconds']:8.3f} "
                f"{row['gflops']:8.1f} {share:>14}"
            )
    return "\n".join(lines)
