"""The benchmark command runs end to end on a tiny case (no timing assertions)."""

from __future__ import annotations

import json

from taptr.cli.main import main


def test_bench_command_on_a_tiny_case(tmp_path, capsys):
    out = tmp_path / "bench.json"
    argv = ["bench", "--preset", "tiny", "--frames", "9", "--points", "5", "--size", "32", "48"]
    assert main([*argv, "--threads", "1", "--flops", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "fast/faithful speed-up" in printed and "command: taptr" in printed
    data = json.loads(out.read_text())
    (case,) = data["cases"]
    assert set(case["results"]) == {"faithful", "fast"}
    fast = case["results"]["fast"]
    assert fast["config"]["size"] == [32, 48] and fast["parameters"] > 0
    assert fast["flops"] > 0 and fast["peak_rss"] > 0
    assert set(fast["stage_seconds"]) == {"backbone", "input_projections", "encoder", "decoder"}
    assert case["agreement"]["max_position_difference"] < 1e-4
    assert case["agreement"]["visibility_decisions_equal"]
