"""``taptr bench --engine ...``: whole videos through each engine, side by side in one process.

For one TAPTRv3 preset (untrained, seeded weights: they set the work, not the tracks), a
random uint8 video and N points on frame 0: ``Predictor.track`` for ``torch`` (capture
off) and the torch-free ``OnnxTracker.track`` over the preset exported once into a
temporary folder for each graph engine, all on the same threads. The cases run in turns
(each once untimed, then ``turns`` rounds) and the best of the rounds is kept: on a shared
machine only times measured together compare.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np


@dataclass(frozen=True)
class EngineCase:
    """One comparison.

    Attributes:
        preset: a TAPTRv3 preset.
        frames: video length T.
        points: query points N (on frame 0).
        size: (H, W) of the video and the model input.
        threads: CPU threads of every engine.
        engines: `taptr.types.ENGINE_CHOICES` to measure.
        turns: timed rounds; the best is kept.
        seed: seed of the weights, video and points.
    """

    preset: str
    frames: int
    points: int
    size: tuple[int, int]
    threads: int
    engines: tuple[str, ...]
    turns: int = 2
    seed: int = 0


def run_engines(case: EngineCase) -> dict[str, float]:
    """Seconds per frame of each engine's whole-video tracking (best of the turns).

    Raises:
        ValueError: a preset other than TAPTRv3's.
    """
    import torch

    from taptr.config import get_config
    from taptr.model.build import build_model

    config = get_config(case.preset)
    if config.version != 3:
        raise ValueError(
            f"--engine compares TAPTRv3 presets; {case.preset} is TAPTR v{config.version}"
        )
    torch.set_num_threads(case.threads)
    torch.manual_seed(case.seed)
    model = build_model(config.replace(input_size=tuple(case.size))).eval()
    rng = np.random.default_rng(case.seed)
    video = rng.integers(0, 256, (case.frames, *case.size, 3), np.uint8)
    height, width = case.size
    xy = rng.uniform(0.05, 0.95, (case.points, 2)) * [width - 1, height - 1]
    queries = np.concatenate([np.zeros((case.points, 1)), xy], 1).astype(np.float32)
    with tempfile.TemporaryDirectory(prefix="taptr-bench-") as folder:
        runs = _trackers(model, case, folder)
        seconds = _in_turns(
            {name: partial(run, video, queries) for name, run in runs.items()}, case
        )
    return {name: value / case.frames for name, value in seconds.items()}


def _trackers(model: Any, case: EngineCase, folder: str) -> dict[str, Callable[..., Any]]:
    """Each engine's whole-video tracking; the graphs are exported once when one needs them."""
    from taptr.api.predictor import Predictor
    from taptr.export.v3_graphs import export_v3
    from taptr.onnx.video_tracker import OnnxTracker

    runs: dict[str, Callable[..., Any]] = {}
    if any(engine != "torch" for engine in case.engines):
        export_v3(model, folder)
    for engine in case.engines:
        if engine == "torch":
            predictor = Predictor(model, device="cpu", capture="off")
            runs[engine] = predictor.track
        else:
            runs[engine] = OnnxTracker(folder, engine=engine, threads=case.threads).track
    return runs


def _in_turns(cases: dict[str, Callable[[], Any]], case: EngineCase) -> dict[str, float]:
    """Each case once untimed, then ``case.turns`` rounds; the best seconds of each."""
    for run in cases.values():
        run()
    best = dict.fromkeys(cases, float("inf"))
    for _ in range(case.turns):
        for name, run in cases.items():
            began = time.perf_counter()
            run()
            best[name] = min(best[name], time.perf_counter() - began)
    return best


def engine_lines(case: EngineCase, seconds: dict[str, float]) -> list[str]:
    """One line per engine: seconds per frame, and the time against torch's when measured."""
    height, width = case.size
    lines = []
    for engine, value in seconds.items():
        against = f" ({value / seconds['torch']:.2f}x torch's time)" if "torch" in seconds else ""
        lines.append(
            f"{case.preset} {engine:11} T={case.frames} N={case.points} {height}x{width} "
            f"{case.threads} threads: {value:.3f} s/frame{against}"
        )
    return lines
