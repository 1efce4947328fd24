"""TAPTRv3's ONNX export, run by the torch-free loop, reproduces the official outputs.

The golden cases of tests/test_golden_v3.py (the official streaming evaluation on the
seed-240716 ResNet-18 weights: 12 frames at 96 × 128; 40 frames at 64 × 96, with and
without a 16-frame history) to the bounds the PyTorch step meets there: 3e-5 on the
normalised positions, 5e-5 on the visibility logits, through every engine (onnxruntime;
OpenVINO where it is installed). One export per input size and test run, shared by the
engines' tests (`tests.export_v3_cases.exported_once`).
"""

from __future__ import annotations

from importlib.util import find_spec

import numpy as np
import pytest

import taptr
from taptr.export.v3_graphs import export_v3
from taptr.onnx.frame_loop import track_points
from taptr.onnx.graph_engines import StepGraphs, open_graphs
from tests.export_v3_cases import exported_once
from tests.helpers import load_golden

pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")

NEEDS_OPENVINO = pytest.mark.skipif(
    find_spec("openvino") is None, reason="openvino is not installed: pip install 'taptr[openvino]'"
)
ENGINES = ["onnxruntime", pytest.param("openvino", marks=NEEDS_OPENVINO)]


def _graphs(checkpoint, base_temp, size: tuple[int, int], engine: str) -> StepGraphs:
    """The golden weights exported once per run at ``size``, opened by ``engine``."""

    def export(folder):
        export_v3(taptr.load_checkpoint(checkpoint), folder, size)

    folder = exported_once(base_temp, f"golden_v3_{size[0]}x{size[1]}", export)
    return open_graphs(folder, engine, threads=1)


def _check(graphs: StepGraphs, case: str, history_frames: int | None) -> None:
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


@pytest.mark.parametrize("engine", ENGINES)
def test_official_12_frames(official_v3_checkpoint, tmp_path_factory, engine):
    base = tmp_path_factory.getbasetemp()
    _check(_graphs(official_v3_checkpoint, base, (96, 128), engine), "v3_r18_small", None)


@pytest.mark.parametrize("engine", ENGINES)
def test_official_40_frames_with_and_without_a_history_limit(
    official_v3_checkpoint, tmp_path_factory, engine
):
    graphs = _graphs(official_v3_checkpoint, tmp_path_factory.getbasetemp(), (64, 96), engine)
    _check(graphs, "v3_r18_long", None)
    _check(graphs, "v3_r18_fifo", 16)
