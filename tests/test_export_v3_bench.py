"""The ONNX benchmark scripts run on the tiny export: the CPU comparison, and the GPU cases
as the dry check they make on a machine without a GPU."""

from __future__ import annotations

import json
import subprocess
import sys
from importlib.util import find_spec
from pathlib import Path

import pytest

from tests.export_v3_cases import tiny_export

pytest.importorskip("onnxruntime")

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _run(script: str, *arguments: str) -> dict:
    """``python benchmarks/<script> ARGUMENTS``'s JSON (the last thing it prints)."""
    done = subprocess.run(
        [sys.executable, str(BENCHMARKS / script), *arguments],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout[done.stdout.index("{\n") :])


def test_cpu_benchmark_times_every_case_side_by_side(tmp_path_factory):
    shared = tiny_export(tmp_path_factory.getbasetemp())
    arguments = ["--checkpoint", str(shared / "tiny_v3.pth"), "--export", str(shared / "graphs")]
    arguments += ["--size", "48", "64", "--frames", "6", "--points", "8", "--turns", "1"]
    engines = ["onnxruntime", "openvino"] if find_spec("openvino") else ["onnxruntime"]
    arguments += ["--engines", *engines]
    report = _run("onnx_v3_cpu.py", *arguments, "--threads", "1", "--skip-capture")
    assert report["machine"]["cpu"] and report["threads"] == 1
    case = report["points"]["8"]
    prefixes = ["onnx", "openvino"][: len(engines)]
    expected = {"step_eager", "predictor_track"}
    expected |= {f"step_{p}" for p in prefixes} | {f"{p}_track" for p in prefixes}
    assert set(case["seconds_per_frame"]) == expected
    for prefix in prefixes:
        assert case[f"{prefix}_step_speed_vs_eager"] > 0
        assert case[f"{prefix}_track_time_vs_predictor"] > 0
        assert case[f"{prefix}_frame_1_max_position_difference"] < 1e-4  # the same model
        assert case[f"{prefix}_track_frame_1_max_pixel_difference"] < 1e-2


def test_gpu_cases_run_on_the_cpu_provider_without_a_gpu(tmp_path_factory):
    graphs = tiny_export(tmp_path_factory.getbasetemp()) / "graphs"
    arguments = ["--device", "cpu", "--preset", "tiny-v3", "--size", "48", "64", "--points", "8"]
    arguments += ["--frames", "6", "--cases", "onnx_taptrv3", "--onnx-export", str(graphs)]
    report = _run("gpu_lean_step.py", *arguments)
    cases = report["onnx_taptrv3"]
    if "CUDAExecutionProvider" in cases["providers"]:
        pytest.skip("a GPU run: its numbers are not checked here")
    assert set(cases) == {"providers", "cpu_float32"}
    assert cases["cpu_float32"]["frame_fps"] > 0 and cases["cpu_float32"]["decode_step_fps"] > 0


def test_gpu_variants_and_their_providers():
    sys.path.insert(0, str(BENCHMARKS))
    try:
        from onnx_gpu_cases import providers, variants
    finally:
        sys.path.remove(str(BENCHMARKS))
    assert variants(["CPUExecutionProvider"]) == [("cpu", "float32")]
    gpu = variants(["TensorrtExecutionProvider", "CUDAExecutionProvider"])
    assert len(gpu) == 6 and ("cuda_graph", "float16") in gpu
    assert providers("cuda_graph", False, "x")[0][1]["enable_cuda_graph"] == "1"
    trt, fallback = providers("tensorrt", True, "cache")
    assert trt[1]["trt_fp16_enable"] == "1" and fallback[0] == "CUDAExecutionProvider"
