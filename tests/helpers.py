"""Paths, loaders and inputs shared by the tests."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from taptr.config import ModelConfig, tiny

FIXTURES = Path(__file__).parent / "fixtures"
SHARED_MEDIA = Path(__file__).resolve().parents[2] / "shared" / "media"


def load_golden(case: str) -> dict[str, np.ndarray]:
    """A compact golden fixture (see scripts/compact_golden.py)."""
    with np.load(FIXTURES / f"{case}.npz") as data:
        return {k: data[k] for k in data.files}


def tiny_v1(**changes) -> ModelConfig:
    """The `tiny` preset as TAPTR v1 (standard attention, no APU, cost volume), then changes."""
    config = tiny().replace(
        version=1,
        cross_attention="standard",
        position_update=False,
        disentangler=False,
        cost_volume=True,
    )
    return config.replace(**changes)


def decode_window_inputs(
    memory: torch.Tensor, points: int, starts: torch.Tensor, generator: torch.Generator
) -> tuple[torch.Tensor, ...]:
    """Random inputs of the exported ``decode_window`` graph around ``memory`` (W_t, S, C).

    Returns memory, content (W_t, N, C), position logits (W_t, N, 4), initial content
    (N, C), and the tracking and update masks (W_t, N) of points starting at ``starts``
    (N,) frames into the window.
    """
    window, _, channels = memory.shape
    offsets = torch.arange(window)[:, None]
    return (
        memory,
        torch.randn(window, points, channels, generator=generator),
        torch.randn(window, points, 4, generator=generator),
        torch.randn(points, channels, generator=generator),
        offsets >= starts,
        offsets > starts,
    )


def run_torchrun(
    args: list[str], processes: int = 2, timeout: float = 180
) -> subprocess.CompletedProcess:
    """``taptr ARGS`` under torchrun with ``processes`` CPU processes (gloo), one thread each."""
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=os.pathsep.join(sys.path))
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone"]
    command += ["--nproc_per_node", str(processes), "-m", "taptr.cli.main"]
    return subprocess.run(
        [*command, *args], env=env, capture_output=True, text=True, timeout=timeout
    )
