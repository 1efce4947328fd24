"""The peak-memory estimate of a tracking run (`taptr.memory_estimate`), against a measurement."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from taptr.config import get_config
from taptr.memory_estimate import (
    MemoryEstimateError,
    allocator_failure,
    available_memory,
    check_memory,
    encoder_tokens,
    estimate_tracking,
)

FACTOR = 1.5
"""The estimate must lie within this factor of the measured peak (docs/FAQ.md)."""

MEASURE = r"""
import json, sys
import numpy as np, torch
from taptr import build_model
from taptr.api.predictor import Predictor
from taptr.memory_estimate import estimate_tracking

def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1]) * 1024

config = build_model("small").config.replace(input_size=(192, 192), context_points=0)
torch.manual_seed(0)
# one frame per encoder call: a measured choice would time the encoder first, and the
# memory that leaves with the allocator would hide part of the peak
predictor = Predictor(build_model(config).eval(), device="cpu", frames_per_call=1)
rng = np.random.default_rng(0)
video = rng.integers(0, 256, (9, 96, 96, 3), dtype=np.uint8)
queries = np.stack([np.zeros(800), rng.uniform(0, 95, 800), rng.uniform(0, 95, 800)], 1)
base = status("VmRSS")
open("/proc/self/clear_refs", "w").write("5")  # the peak starts again from here
predictor.track(video, queries.astype(np.float32))
measured = status("VmHWM") - base
estimate = estimate_tracking(config, input_size=(192, 192), num_frames=9, num_points=800,
                             frame_size=(96, 96), whole_video=False)
print(json.dumps({"measured": measured, "estimate": estimate.total}))
"""


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="needs Linux's /proc")
def test_estimate_is_within_a_factor_of_the_measured_peak_rss():
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=os.pathsep.join(sys.path))
    done = subprocess.run(
        [sys.executable, "-c", MEASURE], capture_output=True, text=True, env=env, check=True
    )
    result = json.loads(done.stdout.strip().splitlines()[-1])
    ratio = result["estimate"] / result["measured"]
    assert 1 / FACTOR <= ratio <= FACTOR, result


def test_the_estimate_grows_with_every_knob():
    config = get_config("taptrv2")
    base = dict(input_size=(512, 512), num_frames=48, num_points=800, frame_size=(480, 854))
    small = estimate_tracking(config, whole_video=False, **base)
    for change in (
        {"input_size": (1024, 1024)},
        {"num_frames": 480},
        {"num_points": 8000},
        {"frame_size": (2160, 3840)},
    ):
        assert estimate_tracking(config, whole_video=False, **dict(base, **change)).total > (
            small.total
        ), change
    assert estimate_tracking(config, whole_video=True, **base).total > small.total
    assert encoder_tokens(512, 512) == 128 * 128 + 64 * 64 + 32 * 32 + 16 * 16


def test_the_paper_model_on_a_huge_grid_or_input_needs_tens_of_gib():
    config = get_config("taptrv2")
    grid = estimate_tracking(
        config, input_size=(512, 512), num_frames=48, num_points=99_856,
        frame_size=(480, 854), whole_video=False,
    )  # fmt: skip
    assert 20 * 1024**3 < grid.total < 60 * 1024**3 and max(grid.parts, key=grid.parts.get) == (
        "points"
    )
    huge = estimate_tracking(
        get_config("small"), input_size=(4096, 4096), num_frames=48, num_points=64,
        frame_size=(256, 256), whole_video=False,
    )  # fmt: skip
    assert huge.total > 16 * 1024**3 and "features" in huge.describe()


def test_over_budget_is_refused_naming_the_knobs_and_the_variable(monkeypatch):
    estimate = estimate_tracking(
        get_config("tiny"), input_size=(64, 64), num_frames=8, num_points=10,
        frame_size=(64, 64), whole_video=True,
    )  # fmt: skip
    monkeypatch.setenv("TAPTR_MAX_MEMORY", "1M")
    assert available_memory() == (1024**2, "TAPTR_MAX_MEMORY")
    with pytest.raises(MemoryEstimateError) as error:
        check_memory(estimate, "tracking 10 points", "lower --input-size")
    message = str(error.value)
    assert "\n" not in message and "lower --input-size" in message and "1 MiB of" in message
    monkeypatch.setenv("TAPTR_MAX_MEMORY", "1T")
    check_memory(estimate, "tracking 10 points", "lower --input-size")
    monkeypatch.delenv("TAPTR_MAX_MEMORY")
    budget, source = available_memory()
    assert budget is None or (budget > 0 and source)


@pytest.mark.parametrize(
    ("error", "named"),
    [
        (MemoryError(), True),
        (RuntimeError("DefaultCPUAllocator: not enough memory: you tried to allocate 9"), True),
        (RuntimeError("CUDA out of memory. Tried to allocate 2.00 GiB"), True),
        (RuntimeError("[enforce fail] DefaultCPUAllocator: can't allocate memory"), True),
        (RuntimeError("shape mismatch"), False),
    ],
)
def test_allocator_failures_are_recognised(error, named):
    message = allocator_failure(error)
    assert (message is not None) == named
    if named:
        assert "--input-size" in message and "--max-frames" in message
