"""Regression tests for hostile input, fourth round (issue 45): kept capture timings,
``--capture on``, fractional frames, many context points, the offline fallback, and the
new user's install lines.

One test (or a parametrised set) per defect, each failing on the code before the fix.
The downloads' bounds are in tests/test_download_bounds.py, the simulated CPUs in
tests/test_cpu_features.py. Everything runs on the tiny presets and fabricated files.
"""

from __future__ import annotations

import argparse
import logging
import re
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from taptr.runtime import step_capture
from taptr.runtime.capture_buckets import points_bucket
from taptr.runtime.capture_timing import CaptureTiming
from taptr.runtime.measured import keep
from taptr.runtime.step_capture import StepCapture
from tests.test_hostile_inputs import _error_line

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _own_measurements(tmp_path, monkeypatch):
    monkeypatch.setenv("TAPTR_MEASURED", str(tmp_path / "measured.json"))


# -- kept capture timings ------------------------------------------------------------------


def _key(points: int) -> str:
    return f"step {points_bucket(points)}"


def _scripted(monkeypatch) -> tuple[object, list[str]]:
    """A decoder and a stand-in captured step; returns the eager one and what ran."""
    ran: list[str] = []

    def eager(*args):
        ran.append("eager")
        return args[0]

    def captured(*args):
        ran.append("captured")
        return args[0]

    monkeypatch.setattr(step_capture, "captured_step", lambda decoder, device: captured)
    return eager, ran


def _run(step: StepCapture, frames: int) -> None:
    for _ in range(frames):
        step(torch.zeros(1, 1, 5, 4))


@pytest.mark.parametrize(
    "kept",
    [
        {"eager_s": 10**400, "captured_s": 0.5, "capture_s": 1.0},  # was an OverflowError
        {"eager_s": 1.0, "captured_s": 0.5, "capture_s": -(10**400)},
        {"eager_s": 1e308, "captured_s": 0.5, "capture_s": 0.0},  # compiled a 6-frame clip
        {"eager_s": 1.0, "captured_s": 0.0, "capture_s": 0.0},  # a step that takes no time
        {"eager_s": 1.0, "captured_s": 0.5, "capture_s": 1e9},  # a capture of 30 years
    ],
)
def test_an_impossible_kept_timing_is_measured_again(monkeypatch, kept):
    assert CaptureTiming.read(kept) is None
    keep(_key(5), kept)
    eager, ran = _scripted(monkeypatch)
    step = StepCapture(eager, torch.device("cpu"), "auto", _key, 5, 6, clock=lambda: 0.0)
    _run(step, 6)
    assert ran == ["eager"] * 6  # six frames never pay for a capture


def test_a_possible_kept_timing_is_still_trusted():
    timing = CaptureTiming.read({"eager_s": 1, "captured_s": 0.5, "capture_s": 40})
    assert timing == CaptureTiming(1.0, 0.5, 40.0)
    failed = CaptureTiming.read({"eager_s": 1.0, "captured_s": float("inf"), "capture_s": 0.0})
    assert failed is not None and not failed.pays(10**9)


def test_capture_on_says_one_line_before_it_compiles(monkeypatch, caplog):
    eager, ran = _scripted(monkeypatch)
    step = StepCapture(eager, torch.device("cpu"), "on", _key, 5, 6, clock=lambda: 0.0)
    with caplog.at_level(logging.WARNING, logger="taptr.runtime.step_capture"):
        _run(step, 3)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and lines[0].startswith("compiling TAPTRv3's per-frame step")
    assert "about 90 s" in lines[0] and ran == ["captured"] * 3


# -- a fractional frame --------------------------------------------------------------------


@pytest.mark.parametrize("text", ["47.0000001,10,10", "0,5,5;3.5,5,5"])
def test_a_fractional_frame_is_an_error_naming_it(text):
    from taptr.cli.common.points import parse_points

    frame = re.search(r"(\d+\.\d+),", text).group(1)
    with pytest.raises(ValueError, match=rf"frame {re.escape(frame)} is not a whole frame index"):
        parse_points(text)


def test_whole_frames_written_as_decimals_are_frames():
    from taptr.cli.common.points import parse_points

    assert parse_points("47.0,10,10;4.7e1,1,2")[:, 0].tolist() == [47.0, 47.0]


def test_a_fractional_frame_in_a_points_file_names_its_line(tmp_path):
    from taptr.cli.common.points import read_points_file

    path = tmp_path / "points.txt"
    path.write_text("t x y\n0 1 1\n47.0000001 10 10\n")
    with pytest.raises(ValueError, match=r"line 3 .*frame 47.0000001 is not a whole frame"):
        read_points_file(str(path))


def test_taptr_track_refuses_a_fractional_frame_on_a_48_frame_clip(tmp_path, capsys):
    from taptr.cli.main import main
    from taptr.io.video import write_video

    frames = np.random.default_rng(0).integers(0, 256, (48, 32, 32, 3), dtype=np.uint8)
    clip = write_video(tmp_path / "clip.mp4", frames, fps=10)
    argv = ["track", str(clip), "--points", "47.0000001,10,10", "--out", str(tmp_path / "o")]
    assert main([*argv, "--checkpoint", "tiny"]) == 2
    assert "frame 47.0000001 is not a whole frame index" in _error_line(capsys, "track")
    assert not (tmp_path / "o").exists()


# -- many context points -------------------------------------------------------------------


def _predictor(context_points: int):
    from taptr import build_model
    from taptr.api.predictor import Predictor
    from taptr.config import get_config

    torch.manual_seed(0)
    model = build_model(get_config("tiny").replace(context_points=800))  # the paper's count
    return Predictor(model, device="cpu", context_points=context_points, frames_per_call=1)


def test_many_context_points_are_in_the_estimate_before_the_run(capsys):
    from taptr.cli.common.run_memory import check_run_memory

    predictor = _predictor(10_000)
    args = argparse.Namespace(backward=False)
    check_run_memory(
        args, predictor, num_frames=48, num_points=1, frame_size=(48, 64), whole_video=False
    )
    err = capsys.readouterr().err
    assert "tracking 10,000 points through 48 frames" in err
    assert "9,999 of the points are context points (--context-points 10000" in err
    assert "the model's own: 800" in err and "about 12x as long as with 800" in err


def test_the_model_s_own_context_points_say_nothing(capsys):
    from taptr.cli.common.run_memory import check_run_memory

    args = argparse.Namespace(backward=False)
    check_run_memory(
        args, _predictor(800), num_frames=48, num_points=1, frame_size=(48, 64), whole_video=False
    )
    assert capsys.readouterr().err == ""


# -- the offline fallback ------------------------------------------------------------------


@pytest.mark.parametrize("timeout", [None, "0.5"])  # the default bound (2 s), and a set one
def test_the_offline_fallback_does_not_wait_for_a_resolver(monkeypatch, tmp_path, caplog, timeout):
    """The 5 s (56 s under load) went to the Hub's name lookup: now bounded, then bundled."""
    pytest.importorskip("huggingface_hub")
    from huggingface_hub import constants

    from taptr.weights import registry

    monkeypatch.setenv("HF_HUB_OFFLINE", "0")
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", False)
    monkeypatch.setenv("HF_ENDPOINT", "https://hub.slow.invalid")
    if timeout is None:
        monkeypatch.delenv("TAPTR_DOWNLOAD_TIMEOUT", raising=False)
    else:
        monkeypatch.setenv("TAPTR_DOWNLOAD_TIMEOUT", timeout)
    bound = float(timeout or 2.0)
    released = threading.Event()
    real = socket.getaddrinfo

    def getaddrinfo(host, *args, **kwargs):
        if isinstance(host, str) and host.endswith(".invalid"):
            released.wait(10.0)  # a resolver that times out
            raise socket.gaierror(socket.EAI_AGAIN, "Temporary failure in name resolution")
        return real(host, *args, **kwargs)

    monkeypatch.setattr(socket, "getaddrinfo", getaddrinfo)
    started = time.perf_counter()
    registry.load_model("taptr-small-synthetic")  # what naming the bundled model costs here
    named = time.perf_counter() - started
    started = time.perf_counter()
    try:
        with caplog.at_level(logging.WARNING):
            choice = registry.load_model(None, cache_dir=tmp_path / "cache")
    finally:
        released.set()
    assert time.perf_counter() - started < named + bound + 3.0  # the bound, and some slack
    assert choice.name == "taptr-small-synthetic"
    assert "the Hub could not be reached" in choice.notice


# -- what a new user reads -----------------------------------------------------------------


def test_install_lines_work_from_a_checkout():
    text = (ROOT / "docs" / "GETTING_STARTED.md").read_text()
    for extras in re.findall(r'pip install "taptr\[([a-z,]+)\]"', text):
        assert f'pip install -e ".[{extras}]"' in text, extras
    assert "published" in text  # the index form is for a release
