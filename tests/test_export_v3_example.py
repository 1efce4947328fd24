"""examples/online_camera_onnx.py on fabricated frames, in a process where torch cannot load."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from taptr.io.video import read_video
from tests.export_v3_cases import tiny_export

pytest.importorskip("onnxruntime")

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "online_camera_onnx.py"

WITHOUT_TORCH = """
import runpy, sys
sys.modules["torch"] = None  # any import of torch now raises ImportError
sys.argv = sys.argv[1:]
runpy.run_path(sys.argv[0], run_name="__main__")
"""


def fabricated_video(path: Path, frames: int = 16) -> Path:
    """A square drifting over noise, written as MPEG-4: (frames, 72, 96) RGB."""
    rng = np.random.default_rng(0)
    background = rng.integers(0, 255, (72, 96, 3), np.uint8)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 24.0, (96, 72))
    for t in range(frames):
        image = background.copy()
        image[20:40, 10 + 2 * t : 30 + 2 * t] = (250, 40, 40)
        writer.write(image)
    writer.release()
    return path


def test_live_example_tracks_fabricated_frames_without_torch(tmp_path_factory, tmp_path):
    graphs = tiny_export(tmp_path_factory.getbasetemp()) / "graphs"
    video = fabricated_video(tmp_path / "fabricated.mp4")
    out = tmp_path / "drawn.mp4"
    command = [sys.executable, "-c", WITHOUT_TORCH, str(EXAMPLE), "--export", str(graphs)]
    command += ["--video", str(video), "--grid", "3", "--refresh", "5", "--threads", "1"]
    done = subprocess.run(
        [*command, "--out", str(out)], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stdout.splitlines()
    per_frame = [line for line in lines if line.startswith("frame ") and line.endswith(" ms")]
    assert len(per_frame) == 16  # the latency of every frame, in the log
    assert any(line.startswith("latency per frame: median") for line in lines)
    assert any("removed" in line and "added 9" in line for line in lines)
    assert read_video(out).shape == (16, 72, 96, 3)  # every frame came back, drawn
