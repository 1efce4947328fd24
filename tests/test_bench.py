"""The benchmark command runs end to end on a tiny case (no timing assertions)."""

from __future__ import annotations

import json

import pytest

from taptr.cli.main import main


def test_bench_command_on_a_tiny_case(tmp_path, capsys):
    out = tmp_path / "bench.json"
    argv = ["bench", "--preset", "tiny", "--frames", "9", "--points", "5", "--size", "32", "48"]
    assert main([*argv, "--threads", "1", "--flops", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "fast/reference speed-up" in printed and "command: taptr" in printed
    data = json.loads(out.read_text())
    (case,) = data["cases"]
    assert set(case["results"]) == {"reference", "fast"}
    fast = case["results"]["fast"]
    assert fast["config"]["size"] == [32, 48] and fast["parameters"] > 0
    assert fast["config"]["execution"] == "fast"
    assert fast["flops"] > 0 and fast["peak_rss"] > 0
    assert set(fast["stage_seconds"]) == {"backbone", "input_projections", "encoder", "decoder"}
    assert case["agreement"]["max_position_difference"] < 1e-4
    assert case["agreement"]["visibility_decisions_equal"]
    # --flops: every stage's FLOPs (the points' content is made outside them), the roofline
    stage_flops = fast["extra"]["stage_flops"]
    assert set(stage_flops) == set(fast["stage_seconds"]) and stage_flops["encoder"] > 0
    assert 0.5 * fast["flops"] < sum(stage_flops.values()) <= fast["flops"]
    assert data["peaks"]["float32"] > 0 and set(data["peaks"]) == {"float32", "bfloat16", "int8"}
    assert "share of peak" in printed and "measured peak on 1 threads" in printed
    assert printed.count("% float32") == 8  # four stages, two executions


def test_roofline_rows_divide_each_stage_by_its_precisions_peak():
    from types import SimpleNamespace

    from taptr.apps.roofline import format_roofline, roofline_rows

    config = {"frames": 2, "dtype": "bfloat16", "preset": "tiny", "execution": "fast"}
    result = SimpleNamespace(
        config=config | {"points": 5},
        stage_seconds={"encoder": 1.0, "decoder": 0.5},
        extra={"stage_flops": {"encoder": 8e9, "decoder": 1e9}},
    )
    peaks = {"float32": 10e9, "bfloat16": 20e9, "int8": None}
    encoder, decoder = roofline_rows(result, peaks)
    assert encoder["gflop"] == 4.0 and encoder["seconds"] == 0.5 and encoder["gflops"] == 8.0
    assert encoder["precision"] == "bfloat16" and encoder["share"] == 0.4
    assert decoder["gflops"] == 2.0 and decoder["share"] == 0.1
    assert "40% bfloat16" in format_roofline([result], peaks)
    result.config = config | {"points": 5, "dtype": "float32"}
    assert "n/a" in format_roofline([result], peaks | {"float32": None})


def test_benchmark_suite_lists_every_case_and_runs_the_smoke_case(tmp_path, capsys):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "suite.py"
    spec = importlib.util.spec_from_file_location("benchmark_suite", path)
    suite = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(suite)
    assert suite.main([*suite.CASES, "--dry-run", "--out", str(tmp_path)]) == 0
    listed = [line for line in capsys.readouterr().out.splitlines() if line.startswith("$ ")]
    assert len(listed) == sum(len(runs) for runs in suite.CASES.values())
    assert all("taptr bench" in line and str(tmp_path) in line for line in listed)
    assert suite.main(["smoke", "--out", str(tmp_path)]) == 0
    (case,) = json.loads((tmp_path / "smoke.json").read_text())["cases"]
    assert case["agreement"]["visibility_decisions_equal"]


TINY_CASE = ["--preset", "tiny", "--size", "64", "--points", "5", "--frames", "9", "--threads", "1"]
"""A tiny case for the scripts in benchmarks/."""


def _benchmark_script(name: str, out, *arguments: str) -> tuple[dict, str]:
    """Runs ``benchmarks/<name>`` on `TINY_CASE`; returns its JSON (written to ``out``) and
    its standard output."""
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "benchmarks" / name
    command = [sys.executable, str(script), *TINY_CASE, *arguments, "--json", str(out)]
    done = subprocess.run(command, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return json.loads(out.read_text()), done.stdout


def test_fast_execution_parts_benchmark_runs_on_a_tiny_case(tmp_path):
    out = tmp_path / "parts.json"
    results, stdout = _benchmark_script("fast_execution_parts.py", out, "--repeats", "2")
    cases = {"channels_last", "in_place_norms", "encoder_block", "shared_tables", "all"}
    cases |= {"onednn_linear", "onednn_linear (encoder)"}
    assert set(results) == {"threads", *cases}
    # the same sums in another order
    assert results["onednn_linear"]["max_abs_difference"] < 1e-4
    # the same arithmetic, bit for bit (the tiny preset's group norms ignore in_place_norms)
    for name in ("encoder_block", "shared_tables", "in_place_norms"):
        assert results[name]["max_abs_difference"] == 0.0
    assert results["all"]["max_abs_difference"] < 1e-4
    assert all(results[name]["speedup_median"] > 0 for name in ("channels_last", "all"))
    assert "speed-up" in stdout
    once = ["fast_execution_parts.py", out, "--repeats", "1"]
    isolated = _benchmark_script(*once, "--processes")[0]["all (separate processes)"]
    assert isolated["off_median_s"] > 0 and isolated["on_median_s"] > 0
    part = _benchmark_script(*once, "--processes", "--part", "in_place_norms")[0]
    assert set(part) == {"threads", "in_place_norms (separate processes)"}
    blocks = _benchmark_script(*once, "--row-block", "3")[0]
    from taptr.model.ops import ROW_BLOCK

    names = [f"{case} (row blocks 3 -> {ROW_BLOCK})" for case in ("encoder", "decoder", "all")]
    assert set(blocks) == {"threads", *names}
    # the same products per row; a 3-row product may take another BLAS kernel's rounding
    assert all(0 <= blocks[name]["max_abs_difference"] < 1e-4 for name in names)


def test_gemm_floor_benchmark_runs_on_a_tiny_case(tmp_path):
    result, stdout = _benchmark_script("gemm_floor.py", tmp_path / "floor.json", "--seconds", "0.2")
    assert result["gflop_per_frame"] > 0 and result["sustained_gflops"] > 0
    expected = result["gflop_per_frame"] / result["sustained_gflops"]
    assert abs(result["floor_at_sustained_s"] - expected) < 1e-9
    paths = (result["sustained_gflops_blas"], result["sustained_gflops_onednn"])
    assert result["sustained_gflops"] == max(paths) and min(paths) > 0
    assert "floor" in stdout and "onednn sustained" in stdout


@pytest.mark.cpu
def test_the_machine_names_its_cpu_model(tmp_path):
    from taptr.apps.benchmark import cpu_name, machine
    from taptr.model.ops.cpu_features import cpu_capability

    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nvendor_id\t: AuthenticAMD\nmodel name\t: AMD EPYC 9R14\n")
    assert cpu_name(cpuinfo) == "AMD EPYC 9R14"
    cpuinfo.write_text("processor\t: 0\n")  # no model name: the architecture instead
    assert cpu_name(cpuinfo) == cpu_name(tmp_path / "missing") != ""
    # taptr's view of the CPU: PyTorch's, lowered by TAPTR_CPU when it is set
    assert machine()["cpu_capability"] == cpu_capability()


@pytest.mark.cpu
def test_bench_refuses_bfloat16_on_a_cpu_without_it(simulated_cpu, capsys):
    simulated_cpu("avx512")
    argv = ["bench", "--preset", "tiny", "--frames", "9", "--points", "5", "--dtype", "bfloat16"]
    assert main(argv) == 2
    assert "this CPU has no native bfloat16" in capsys.readouterr().err


def test_bench_refuses_float16_on_the_cpu(capsys):
    argv = ["bench", "--preset", "tiny", "--frames", "9", "--points", "5", "--dtype", "float16"]
    assert main(argv) == 2
    assert "--dtype float16 is CUDA autocast" in capsys.readouterr().err


@pytest.mark.cpu
def test_bench_compares_dtypes_in_one_command(tmp_path, capsys):
    from taptr.model.ops.dense import native_bfloat16

    if not native_bfloat16():
        pytest.skip("this CPU has no native bfloat16")
    out = tmp_path / "types.json"
    argv = ["bench", "--preset", "tiny", "--frames", "9", "--points", "5", "--size", "32", "48"]
    options = ["--execution", "fast", "--dtype", "float32", "bfloat16", "--threads", "1"]
    assert main([*argv, *options, "--json", str(out)]) == 0
    assert "bfloat16" in capsys.readouterr().out
    (case,) = json.loads(out.read_text())["cases"]
    assert set(case["results"]) == {"float32", "bfloat16"}
    change = case["against_float32"]["bfloat16"]
    assert change["speedup"] > 0 and change["visibility_decisions"] == 9 * 5
    assert 0 < change["max_position_change_px"] < 5
    assert main([*argv, "--dtype", "float32", "bfloat16"]) == 2  # one execution at a time


def test_decoder_step_benchmark_runs_on_a_tiny_case(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    script = root / "benchmarks" / "decoder_step.py"
    case = ["--preset", "tiny-v3", "--size", "48", "64", "--queries", "3", "--frames", "3"]
    case += ["--turns", "1", "--threads", "1"]
    for extra in ([], ["--against", str(root / "src")]):
        out = tmp_path / "step.json"
        command = [sys.executable, str(script), *case, *extra, "--json", str(out)]
        done = subprocess.run(command, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        (result,) = json.loads(out.read_text())["queries"].values()
        assert result["model_points"] == 3 + 36  # the predictor's grid of support points
        assert all(seconds > 0 for seconds in result["seconds_per_frame"].values())
        assert result["max_position_difference"] < 1e-4
