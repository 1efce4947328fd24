"""Speed and memory benchmark of the model, each configuration in its own process.

A run tracks N random points (all starting on frame 0) through T random frames with
random (seeded) weights and reports wall time per frame, a per-stage breakdown (backbone,
input projections, encoder, decoder), peak resident memory, peak CUDA memory, parameters
and, optionally, FLOPs. Two executions (`taptr.model.execution`) are compared in the same
command:

- ``reference``: the straightforward formulation (``grid_sample`` deformable attention,
  N × N attention masks, MLPs on all rows at once), with every frame encoded up front in
  chunks of 24, as the official evaluation does;
- ``fast``: the default (gather kernel, point attention on tracked points only, MLPs in
  row blocks), with frames encoded once per window and dropped when no window needs them.

Each execution runs in a fresh subprocess so that peak memory is its own. FLOPs come from
``torch.utils.flop_counter`` (2 per multiply-accumulate; convolutions, matmuls and
attention counted with the math SDPA backend; bilinear sampling and gathers not counted).
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor, nn

from taptr.memory_estimate import ALLOCATOR_WORDS
from taptr.model.ops.cpu_features import bfloat16_hardware, cpu_capability, simulated
from taptr.model.ops.dense import linear, onednn_applies
from taptr.runtime.measured import cpu_name

if TYPE_CHECKING:
    from taptr.model.taptr import TAPTR

EXECUTIONS = ("reference", "fast")
"""The executions `compare` runs, baseline first."""
STAGES = ("backbone", "input_projections", "encoder", "decoder")


@dataclass(frozen=True)
class BenchConfig:
    """One benchmark case.

    Attributes:
        preset: model preset (``taptrv2``, ``taptrv3``, ``taptrv3-r50``, ``taptrv1``,
            ``small``, ``tiny``).
        frames: video length T.
        points: query points N.
        size: (height, width) of the model input.
        threads: torch CPU threads.
        device: ``cpu`` or ``cuda``.
        dtype: ``float32``; ``bfloat16`` / ``float16`` autocast on CUDA; ``bfloat16``
            products through oneDNN on CPUs with native bfloat16
            (`taptr.model.ops.dense.bfloat16_products`).
        execution: ``reference`` or ``fast`` (`taptr.model.execution.EXECUTIONS`).
        flops: also count FLOPs (a second, slower pass).
        seed: seed of the weights, video and queries.
        history_frames: TAPTRv3's history limit (None: the model's, the whole video).
        compile: compile the model's heavy parts first (`taptr.runtime.compile.compile_model`).
        frames_per_call: frames per encoder call of the fast execution, ``auto`` as the
            predictor chooses (`taptr.runtime.encode_choice`, measured once per machine and
            shape before the clock starts) or a number; the reference execution encodes
            all frames up front.

    On CUDA the case runs once untimed before the timed run, so that kernel selection,
    the allocator's first growth and compilation are not counted.
    """

    preset: str = "taptrv2"
    frames: int = 24
    points: int = 800
    size: tuple[int, int] = (512, 512)
    threads: int = 2
    device: str = "cpu"
    dtype: str = "float32"
    execution: str = "fast"
    flops: bool = False
    seed: int = 0
    history_frames: int | None = None
    compile: bool = False
    frames_per_call: int | str = "auto"


@dataclass
class BenchResult:
    """Measurements of one case (times in seconds, memory in bytes).

    ``extra["step_seconds"]`` holds the wall time of each window (TAPTRv2) or frame
    (TAPTRv3) in order, encoding included where it happens then; ``extra["stage_flops"]``
    the FLOPs of each stage over the run when they were counted (else None).
    """

    config: dict[str, Any]
    seconds_per_frame: float
    stage_seconds: dict[str, float]
    peak_rss: int
    peak_cuda: int | None
    parameters: int
    flops: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)


@contextmanager
def _stage_timer(model: nn.Module, device: str) -> Iterator[dict[str, float]]:
    """Accumulates wall time spent in each top-level stage of the model."""
    totals: dict[str, float] = defaultdict(float)
    starts: dict[str, float] = {}
    handles = []

    def sync() -> None:
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    for name in STAGES:
        module = getattr(model, name)

        def before(*_: Any, name: str = name) -> None:
            sync()
            starts[name] = time.perf_counter()

        def after(*_: Any, name: str = name) -> None:
            sync()
            totals[name] += time.perf_counter() - starts[name]

        handles += [module.register_forward_pre_hook(before), module.register_forward_hook(after)]
    try:
        yield totals
    finally:
        for handle in handles:
            handle.remove()


def _inputs(config: BenchConfig) -> tuple[torch.Tensor, Any]:
    from taptr.model.trajectory import QuerySet

    generator = torch.Generator().manual_seed(config.seed)
    # uint8 frames, as a decoded video: holding 300 frames as float32 would be most of the
    # fast execution's memory
    shape = (1, config.frames, 3, *config.size)
    video = torch.randint(0, 256, shape, generator=generator, dtype=torch.uint8)
    queries = QuerySet(
        torch.zeros(1, config.points, dtype=torch.long),
        torch.rand(1, config.points, 2, generator=generator) * 0.9 + 0.05,
        torch.ones(1, config.points, dtype=torch.bool),
    )
    return video, queries


def _track(
    model: TAPTR,
    config: BenchConfig,
    video: torch.Tensor,
    queries: Any,
    steps: list[float] | None = None,
    frames_per_call: int = 1,
) -> Any:
    from taptr.model.taptr import normalize_frames
    from taptr.model.trajectory import QuerySet
    from taptr.runtime.engines import run_tracker
    from taptr.runtime.frames import EncodedFrames, PrecomputedFrames

    device = torch.device(config.device)
    video = video.to(device)
    queries = QuerySet(*(q.to(device) for q in queries))

    def load(first: int, last: int) -> torch.Tensor:
        return normalize_frames(video[:, first : last + 1].float() / 255)

    frames: EncodedFrames | PrecomputedFrames
    if config.execution == "reference":
        # the official code's way: the whole video in float, every frame encoded up front
        frames = PrecomputedFrames(model.encode(load(0, config.frames - 1), chunk_size=24))
    else:
        frames = EncodedFrames(model, load, frames_per_call, config.frames)
    marks = [time.perf_counter()]

    def on_step() -> None:
        if config.device.startswith("cuda"):
            torch.cuda.synchronize()
        marks.append(time.perf_counter())
        if steps is not None:
            steps.append(marks[-1] - marks[-2])

    return run_tracker(
        model,
        queries,
        config.frames,
        frames,
        torch.float32,
        on_step,
        history_frames=config.history_frames,
    )


def run_case(config: BenchConfig, positions_out: str | None = None) -> BenchResult:
    """Runs one case in this process (use `run_isolated` for a clean peak-memory reading)."""
    from taptr.model.build import build_model
    from taptr.runtime.cpu_choice import choose_cpu_execution
    from taptr.runtime.encode_choice import choose_frames_per_call

    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    model = build_model(config.preset, execution=config.execution).eval().to(config.device)
    if config.dtype == "bfloat16" and config.device == "cpu":
        model.bfloat16_trunk()
    if config.compile:
        from taptr.runtime.compile import compile_model

        compile_model(model)
    video, queries = _inputs(config)
    autocast = _precision(config)
    per_call = 1  # the reference execution encodes every frame up front (`_track`)
    if config.execution != "reference":
        with _precision(config):  # as the predictor chooses
            if config.device == "cpu":
                choose_cpu_execution(model, config.size)
            per_call = choose_frames_per_call(
                model, torch.device(config.device), config.size, config.frames_per_call
            )
    if config.device.startswith("cuda"):
        with torch.no_grad(), _precision(config):
            _track(model, config, video, queries, frames_per_call=per_call)
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    steps: list[float] = []
    with torch.no_grad(), autocast, _stage_timer(model, config.device) as stages:
        start = time.perf_counter()
        output = _track(model, config, video, queries, steps, per_call)
        if config.device.startswith("cuda"):
            torch.cuda.synchronize()
        elapsed = time.perf_counter() - start
    if positions_out:
        np.save(positions_out, output.positions[0].float().cpu().numpy())
        np.save(
            positions_out + ".logits.npy", output.visibility_logits[0, ..., 1].float().cpu().numpy()
        )
    # read before counting FLOPs: the counter runs attention unfused, at a far higher peak
    peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    cuda = config.device.startswith("cuda")
    peak_cuda = torch.cuda.max_memory_allocated() if cuda else None
    flops, stage_flops = (
        _count_flops(model, config, video, queries) if config.flops else (None, None)
    )
    return BenchResult(
        config=asdict(config),
        seconds_per_frame=elapsed / config.frames,
        stage_seconds=dict(stages),
        peak_rss=peak_rss,
        peak_cuda=peak_cuda,
        parameters=sum(p.numel() for p in model.parameters()),
        flops=flops,
        extra={
            "step_seconds": steps,
            "frames_per_call": per_call,
            "onednn_linear": model.execution.onednn_linear,
            "channels_last": model.execution.channels_last,
            "stage_flops": stage_flops,
        },
    )


def _precision(config: BenchConfig) -> contextlib.AbstractContextManager[object]:
    """What the predictor runs in for this dtype (`taptr.runtime.precision.precision_context`)."""
    from taptr.runtime.precision import autocast_type, precision_context

    return precision_context(torch.device(config.device).type, autocast_type(config.dtype))


def seconds_per_frame_at(result: BenchResult, frame: int, span: int = 8) -> float | None:
    """Mean wall time of the ``span`` frames up to ``frame`` (1-based) of a per-frame run.

    None for a windowed model (its steps are windows) or a run shorter than ``frame``.
    """
    steps = result.extra.get("step_seconds") or []
    if len(steps) != result.config["frames"] or frame > len(steps):
        return None
    window = steps[max(0, frame - span) : frame]
    return float(np.mean(window))


def _count_flops(
    model: TAPTR, config: BenchConfig, video: torch.Tensor, queries: Any
) -> tuple[int, dict[str, int]]:
    """FLOPs of the whole run and of each stage (`taptr.apps.roofline.stage_flops`)."""
    from torch.nn.attention import SDPBackend, sdpa_kernel
    from torch.utils.flop_counter import FlopCounterMode

    from taptr.apps.roofline import stage_flops

    counter = FlopCounterMode(display=False)
    flops_of = stage_flops(model, STAGES, counter)
    with torch.no_grad(), sdpa_kernel(SDPBackend.MATH), counter, flops_of as stages:
        _track(model, config, video, queries)
    return int(counter.get_total_flops()), dict(stages)


def run_isolated(config: BenchConfig, positions_out: str | None = None) -> BenchResult:
    """Runs one case in a fresh Python process and returns its measurements."""
    payload = json.dumps({"config": asdict(config), "positions_out": positions_out})
    command = [sys.executable, "-m", "taptr.apps.benchmark", payload]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        # the worker's last line names its error; the traceback above it is for developers
        last = (done.stderr.strip().splitlines() or [f"exit status {done.returncode}"])[-1]
        if last.startswith("MemoryError") or any(w in last.lower() for w in ALLOCATOR_WORDS):
            raise ValueError(
                f"benchmark worker ran out of memory ({last[:300]}); use fewer --frames, "
                "fewer --points or a smaller --size"
            )
        raise RuntimeError(f"benchmark worker failed: {last[:500]}")
    data = json.loads(done.stdout.strip().splitlines()[-1])
    return BenchResult(**data)


def compare(base: BenchConfig) -> dict[str, Any]:
    """Runs the reference and the fast execution of a case; returns both and their agreement."""
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in EXECUTIONS:
            out = os.path.join(tmp, f"{name}.npy")
            results[name] = run_isolated(_with(base, execution=name), out)
        reference, fast = (np.load(os.path.join(tmp, f"{e}.npy")) for e in EXECUTIONS)
        logits = [np.load(os.path.join(tmp, f"{e}.npy.logits.npy")) for e in EXECUTIONS]
    firm = np.abs(logits[0]) >= 1e-4
    agreement = {
        "max_position_difference": float(np.abs(reference - fast).max()),
        "visibility_decisions_equal": bool(((logits[0] > 0) == (logits[1] > 0))[firm].all()),
        "speedup": results["reference"].seconds_per_frame / results["fast"].seconds_per_frame,
        "memory_ratio": results["fast"].peak_rss / results["reference"].peak_rss,
    }
    return {"results": results, "agreement": agreement}


def compare_types(base: BenchConfig, dtypes: list[str]) -> dict[str, Any]:
    """Runs one execution of a case in each dtype, each in its own process.

    Returns the results and how each dtype differs from the first: speed and peak-memory
    ratios, position changes in pixels of the model input, visibility decisions flipped.
    """
    results, positions, logits = {}, {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for dtype in dtypes:
            out = os.path.join(tmp, f"{dtype}.npy")
            results[dtype] = run_isolated(_with(base, dtype=dtype), out)
            positions[dtype], logits[dtype] = np.load(out), np.load(out + ".logits.npy")
    first = dtypes[0]
    height, width = base.size
    scale = np.array([width - 1, height - 1])  # normalised → pixels of the model input
    against = {}
    for dtype in dtypes[1:]:
        moved = np.abs(positions[dtype] - positions[first]) * scale
        flips = (logits[dtype] > 0) != (logits[first] > 0)
        against[dtype] = {
            "speedup": results[first].seconds_per_frame / results[dtype].seconds_per_frame,
            "memory_ratio": results[dtype].peak_rss / results[first].peak_rss,
            "max_position_change_px": float(moved.max()),
            "median_position_change_px": float(np.median(moved)),
            "visibility_flips": int(flips.sum()),
            "visibility_decisions": int(flips.size),
        }
    return {"results": results, "against_" + first: against}


def _with(config: BenchConfig, **changes: Any) -> BenchConfig:
    return BenchConfig(**{**asdict(config), **changes})


def machine() -> dict[str, Any]:
    """What the numbers were measured on."""
    info: dict[str, Any] = {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpu": cpu_name(),
        "cpu_capability": cpu_capability(),
        "cpu_count": os.cpu_count(),
        "cpu_bfloat16": bfloat16_hardware(),
    }
    if simulated() is not None:  # a lesser CPU than the host, by TAPTR_CPU
        info["cpu_simulated"] = simulated()
    if torch.cuda.is_available():
        info["cuda_device"] = torch.cuda.get_device_name()
    return info


def format_table(rows: list[BenchResult]) -> str:
    """A plain-text table of results."""
    header = (
        f"{'preset':8} {'execution':9} {'T':>4} {'N':>6} {'size':>9} {'s/frame':>8} "
        + " ".join(f"{s[:8]:>8}" for s in STAGES)
        + f" {'peak RSS':>9} {'params':>11} {'GFLOP/frame':>11}"
    )
    lines = [header]
    for row in rows:
        c = row.config
        preset = (
            c["preset"]
            if c.get("history_frames") is None
            else f"{c['preset']}/h{c['history_frames']}"
        )
        stages = " ".join(f"{row.stage_seconds.get(s, 0.0) / c['frames']:8.3f}" for s in STAGES)
        gflops = f"{row.flops / c['frames'] / 1e9:11.1f}" if row.flops else f"{'-':>11}"
        size = f"{c['size'][0]}x{c['size'][1]}"
        short = {"float32": "", "bfloat16": "/bf16", "float16": "/fp16"}[c["dtype"]]
        execution = c["execution"] + short
        lines.append(
            f"{preset:8} {execution:9} {c['frames']:4d} {c['points']:6d} {size:>9} "
            f"{row.seconds_per_frame:8.3f} {stages} {row.peak_rss / 2**30:8.2f}G "
            f"{row.parameters:11,d} {gflops}"
        )
    return "\n".join(lines)


def peak_flops(threads: int, size: int = 2048, repeats: int = 5) -> float:
    """Measured fp32 matrix-product FLOP rate of this machine (FLOP/s), the roofline reference.

    The best of ``repeats`` ``size``³ products through each path the model's products can
    take: the BLAS (``torch.mm``) and, where it applies, oneDNN's inner product
    (`taptr.model.ops.dense`), which ran twice as fast as MKL on the AMD host measured.
    """
    torch.set_num_threads(threads)
    a, b = torch.randn(size, size), torch.randn(size, size)
    weight = b.t().contiguous()  # (out, in): a @ b as a linear layer
    products: list[Callable[[], Tensor]] = [lambda: torch.mm(a, b)]
    if onednn_applies(a, weight):
        products.append(lambda: linear(a, weight, None, onednn=True))
    best = float("inf")
    for product in products:
        product()
        for _ in range(repeats):
            start = time.perf_counter()
            product()
            best = min(best, time.perf_counter() - start)
    return 2 * size**3 / best


def write_json(path: str | os.PathLike[str], data: Any) -> Path:
    """Writes results as JSON, atomically."""
    from taptr.io.atomic import atomic_path

    def default(obj: Any) -> Any:
        if isinstance(obj, BenchResult):
            return asdict(obj)
        raise TypeError(type(obj).__name__)

    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=1, default=default) + "\n")
    return Path(path)


def main() -> None:
    """Worker entry point: ``python -m taptr.apps.benchmark '<request>'`` prints a JSON line."""
    request = json.loads(sys.argv[1])
    config = BenchConfig(**{**request["config"], "size": tuple(request["config"]["size"])})
    result = run_case(config, request.get("positions_out"))
    sys.stdout.write(json.dumps(asdict(result)) + "\n")


if __name__ == "__main__":
    main()
