"""``taptr eval`` under torchrun (2 processes, gloo) gives the single-process result."""

from __future__ import annotations

import json

from taptr.cli.main import main
from tests.helpers import run_torchrun
from tests.test_tapvid_fabricated import make_clip, write_davis


def _scores(path):
    report = json.loads(path.read_text())
    videos = [{k: v for k, v in video.items() if k != "seconds"} for video in report["videos"]]
    return report, videos, report["mean"]


def test_two_processes_equal_one(tmp_path, capsys):
    clips = [make_clip(8 + 2 * k, seed=k, name=f"clip{k}") for k in range(3)]
    root = write_davis(tmp_path / "tapvid_davis.pkl", clips)
    args = ["eval", "--dataset", "davis", "--root", str(root), "--tracker", "lk"]
    args += ["--mode", "strided"]
    assert main([*args, "--out", str(tmp_path / "one")]) == 0
    capsys.readouterr()

    done = run_torchrun([*args, "--device", "cpu", "--out", str(tmp_path / "two")], timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.count("wrote") == 2  # the main process alone reports

    one, one_videos, one_mean = _scores(tmp_path / "one" / "results.json")
    two, two_videos, two_mean = _scores(tmp_path / "two" / "results.json")
    assert two["config"]["world_size"] == 2 and one["config"]["world_size"] == 1
    assert [v["name"] for v in two_videos] == ["clip0", "clip1", "clip2"]
    assert two_videos == one_videos
    assert two_mean == one_mean
