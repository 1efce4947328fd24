"""Engines' precisions: int8 graphs made once and tracking near float32, bfloat16 where the
CPU has it, and one-line refusals of what an engine or CPU cannot do."""

from __future__ import annotations

import shutil
from importlib.util import find_spec

import numpy as np
import pytest

from taptr.onnx.calibration_frames import calibration_frames
from taptr.onnx.graph_engines import open_graphs
from taptr.onnx.int8_graphs import FOLDER, RECORD
from taptr.onnx.video_tracker import OnnxTracker
from tests.export_v3_cases import tiny_export

pytest.importorskip("onnxruntime")

NEEDS_OPENVINO = pytest.mark.skipif(
    find_spec("openvino") is None, reason="openvino is not installed: pip install 'taptr[openvino]'"
)

VIDEO = np.random.default_rng(3).integers(0, 256, (8, 48, 64, 3), np.uint8)
QUERIES = np.array([[0, 5.0, 7.0], [2, 33.0, 20.5], [5, 60.0, 40.0]], np.float32)


@pytest.fixture(scope="module")
def graphs(tmp_path_factory):
    """A copy of the shared tiny export: the int8 folder is made inside it."""
    shared = tiny_export(tmp_path_factory.getbasetemp()) / "graphs"
    own = tmp_path_factory.mktemp("precision") / "graphs"
    shutil.copytree(shared, own)
    return own


def _bfloat16_cpu() -> bool:
    import openvino

    return "BF16" in openvino.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES")


def _pixel_difference(graphs, engine: str, precision: str) -> float:
    expected = OnnxTracker(graphs, engine=engine, threads=1).track(VIDEO, QUERIES)
    got = OnnxTracker(graphs, engine=engine, threads=1, precision=precision).track(VIDEO, QUERIES)
    return float(np.abs(got.tracks - expected.tracks).mean())


def test_calibration_frames_are_textured_and_refuse_bad_sizes():
    frames = calibration_frames(5, (32, 40), seed=1)
    assert frames.shape == (5, 3, 32, 40) and frames.dtype == np.float32
    assert frames.min() >= 0 and frames.max() <= 1 and frames.std() > 0.1
    np.testing.assert_array_equal(frames, calibration_frames(5, (32, 40), seed=1))
    with pytest.raises(ValueError, match="at least 8 pixels"):
        calibration_frames(1, (4, 40))


def test_int8_onnxruntime_tracks_near_float32_and_is_made_once(graphs, capfd):
    # the tiny model's random weights amplify quantisation noise more than a trained one;
    # a broken int8 graph (wrong scales, a swapped input) moves points by tens of pixels
    assert _pixel_difference(graphs, "onnxruntime", "int8") < 1.5  # 48 × 64 frames
    assert "made int8 encoder" in capfd.readouterr().err
    record = (graphs / FOLDER / RECORD).read_text()
    open_graphs(graphs, "onnxruntime", precision="int8", threads=1)
    assert "made int8" not in capfd.readouterr().err  # kept, not made again
    assert (graphs / FOLDER / RECORD).read_text() == record


def test_int8_is_made_again_when_the_export_changes(graphs, capfd):
    open_graphs(graphs, "onnxruntime", precision="int8", threads=1)
    capfd.readouterr()
    (graphs / FOLDER / RECORD).write_text('{"sources": {}}')  # another export's record
    open_graphs(graphs, "onnxruntime", precision="int8", threads=1)
    assert "made int8 encoder" in capfd.readouterr().err


def test_onnxruntime_refuses_bfloat16_and_unknown_precisions_in_one_line(graphs):
    with pytest.raises(ValueError, match="engine='openvino'") as refused:
        open_graphs(graphs, "onnxruntime", precision="bfloat16")
    assert "\n" not in str(refused.value)
    with pytest.raises(ValueError, match="precision must be one of float32, bfloat16, int8"):
        open_graphs(graphs, "onnxruntime", precision="fp16")


@NEEDS_OPENVINO
def test_int8_openvino_tracks_near_float32(graphs):
    assert _pixel_difference(graphs, "openvino", "int8") < 1.5


@NEEDS_OPENVINO
def test_bfloat16_openvino_tracks_near_float32(graphs):
    if not _bfloat16_cpu():
        pytest.skip("this CPU has neither AVX512-BF16 nor AMX (the refusal is tested below)")
    assert _pixel_difference(graphs, "openvino", "bfloat16") < 1.5


@NEEDS_OPENVINO
def test_bfloat16_openvino_is_refused_without_the_cpu_feature(graphs, monkeypatch):
    monkeypatch.setenv("TAPTR_CPU", "avx512")
    from taptr import cpu_levels

    cpu_levels.ceiling.cache_clear()
    try:
        with pytest.raises(ValueError, match="AVX512-BF16 or AMX") as refused:
            open_graphs(graphs, "openvino", precision="bfloat16")
    finally:
        monkeypatch.delenv("TAPTR_CPU")
        cpu_levels.ceiling.cache_clear()
    assert "\n" not in str(refused.value) and "TAPTR_CPU=avx512" in str(refused.value)
