"""TAPTRv3's ONNX export, run by the torch-free loop, reproduces the official outputs.

The golden cases of tests/test_golden_v3.py (the official streaming evaluation on the
seed-240716 ResNet-18 weights: 12 frames at 96 × 128; 40 frames at 64 × 96, with and
without a 16-frame history) to the bounds the PyTorch step meets there: 3e-5 on the
normalised positions, 5e-5 on the visibility logits. One export per input size, each in
its own test so that two workers export in parallel.
"""

from __future__ import annotations

import numpy as np
import pytest

import taptr
from taptr.export.v3_graphs import export_v3
from taptr.onnx.frame_loop import track_points
from taptr.onnx.ort_engine import OnnxRuntimeGraphs as OnnxGraphs
from tests.helpers import load_golden

pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")


def _check(graphs: OnnxGraphs, case: str, history_frames: int | None) -> None:
    golden = load_golden(case)
    video = golden["in_video_u8"][0].astype(np.float32) / 255  # (T, 3, H, W) in [0, 1]
    out = track_points(
        graphs,
        video,
        len(video),
        golden["in_query_t"],
        golden["in_query_xy_norm"].astype(np.float32),
        golden["in_query_label"] == 1,
        history_frames,
    )
    positions = out.positions.transpose(1, 0, 2)  # (N, T, 2), point-major as the fixtures
    logits = out.visibility_logits.transpose(1, 0, 2)
    assert np.abs(positions - golden["out_pred_xy_norm"]).max() <= 3e-5
    assert np.abs(logits - golden["out_vis_logits"]).max() <= 5e-5
    written = np.arange(positions.shape[1])[None] > golden["in_query_t"][:, None]
    firm = written & (np.abs(golden["out_vis_logits"][..., 1] - np.log(0.45 / 0.55)) >= 1e-4)
    visible = 1 / (1 + np.exp(-logits[..., 1])) > 0.45
    assert (visible == golden["out_visible"])[firm].all()


def test_official_12_frames(official_v3_checkpoint, tmp_path):
    model = taptr.load_checkpoint(official_v3_checkpoint)
    export_v3(model, tmp_path, (96, 128))
    _check(OnnxGraphs(tmp_path, threads=1), "v3_r18_small", None)


def test_official_40_frames_with_and_without_a_history_limit(official_v3_checkpoint, tmp_path):
    model = taptr.load_checkpoint(official_v3_checkpoint)
    export_v3(model, tmp_path, (64, 96))
    graphs = OnnxGraphs(tmp_path, threads=1)
    _check(graphs, "v3_r18_long", None)
    _check(graphs, "v3_r18_fifo", 16)
