"""Every example runs (--help, then on generated media with the tiny untrained model)."""

from __future__ import annotations

import importlib.util
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from taptr.data.sample_video import write_sample_video
from taptr.io.tracks import load_tracks_npz
from taptr.io.video import read_video

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SCRIPTS = sorted(p.stem for p in EXAMPLES.glob("*.py"))


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def sample(tmp_path_factory) -> Path:
    return write_sample_video(tmp_path_factory.mktemp("media") / "sample.mp4")


def test_every_example_is_listed_and_tested():
    listed = (EXAMPLES / "README.md").read_text()
    assert all(f"`{name}.py`" in listed for name in SCRIPTS)
    assert set(SCRIPTS) == set(RUNS)


@pytest.mark.parametrize("name", SCRIPTS)
def test_help(name, capsys):
    with pytest.raises(SystemExit) as exit_info:
        _load(name).main(["--help"])
    assert exit_info.value.code == 0
    assert "usage:" in capsys.readouterr().out


def _track_video(tmp_path, sample, capsys):
    out = tmp_path / "out"
    argv = [str(sample), "--grid", "3", "--backward", "--max-frames", "12"]
    assert _load("track_video").main([*argv, "--checkpoint", "tiny", "--out", str(out)]) == 0
    saved = load_tracks_npz(out / "tracks.npz")
    assert saved.tracks.shape == (12, 9, 2) and saved.visibility.shape == (12, 9)
    assert read_video(out / "overlay.mp4").shape == (12, 256, 256, 3)
    assert (out / "tracks.csv").is_file()


def _online_camera(tmp_path, sample, capsys):
    out = tmp_path / "online.mp4"
    argv = ["--video", str(sample), "--max-frames", "20", "--refresh", "8", "--grid", "3"]
    assert _load("online_camera").main([*argv, "--checkpoint", "tiny", "--out", str(out)]) == 0
    assert read_video(out).shape == (20, 256, 256, 3)  # every frame came back, in order


def _online_camera_onnx(tmp_path, sample, capsys):
    from tests.export_v3_cases import tiny_export

    graphs = tiny_export(tmp_path.parent) / "graphs"  # shared with tests/test_export_v3_onnx.py
    out = tmp_path / "online_onnx.mp4"
    argv = ["--export", str(graphs), "--video", str(sample), "--max-frames", "12", "--grid", "3"]
    assert _load("online_camera_onnx").main([*argv, "--refresh", "6", "--out", str(out)]) == 0
    assert read_video(out).shape == (12, 256, 256, 3)


def _edit_region(tmp_path, sample, capsys):
    out = tmp_path / "edited.mp4"
    argv = ["--max-frames", "10", "--stride", "12", "--checkpoint", "tiny", "--out", str(out)]
    assert _load("edit_region").main(argv) == 0
    assert read_video(out).shape == (10, 256, 256, 3)


def _sample_video(tmp_path, sample, capsys):
    out = tmp_path / "clip.mp4"
    argv = ["--frames", "6", "--size", "64", "96", "--grid", "3", "--out", str(out)]
    assert _load("sample_video").main(argv) == 0
    assert read_video(out).shape == (6, 64, 96, 3)
    truth = load_tracks_npz(tmp_path / "clip_truth.npz")
    np.testing.assert_allclose(truth.tracks[0], truth.queries[:, 1:], atol=1e-4)


def _evaluate(tmp_path, sample, capsys):
    argv = ["--videos", "1", "--frames", "8", "--checkpoint", "tiny", "--device", "cpu"]
    assert _load("evaluate").main(argv) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines[-3:]] == ["taptr", "static", "lk"]


def _convert_checkpoint(tmp_path, sample, capsys):
    import taptr

    source = taptr.save_checkpoint(taptr.build_model("tiny"), tmp_path / "source.pth")
    half = tmp_path / "half.pth"
    assert _load("convert_checkpoint").main([str(source), str(half), "--half"]) == 0
    assert taptr.load_checkpoint(half).config == taptr.get_config("tiny")
    assert _load("convert_checkpoint").main([]) == 0  # the demo: writes outputs/ in the cwd
    assert (tmp_path / "outputs" / "converted.pth").is_file()


def _benchmark(tmp_path, sample, capsys):
    argv = ["--preset", "tiny", "--frames", "4", "--points", "2", "--size", "32", "32"]
    assert _load("benchmark").main([*argv, "--threads", "1"]) == 0
    assert capsys.readouterr().out.splitlines()[-1].split()[0] == "2"


def _train_small(tmp_path, sample, capsys):
    argv = ["--out", str(tmp_path / "run"), "--videos", "2", "--size", "64", "--steps", "1"]
    assert _load("train_small").main([*argv, "--preset", "tiny", "data.num_points=16"]) == 0
    assert (tmp_path / "run" / "model.pt").is_file()


def _calibrate_threshold(tmp_path, sample, capsys):
    out = tmp_path / "calibrated.pth"
    argv = ["--checkpoint", "tiny", "--videos", "1", "--out", str(out)]
    assert _load("calibrate_threshold").main(argv) == 0
    from taptr.weights.checkpoint import read_visibility_threshold

    assert 0 < read_visibility_threshold(out) < 1


RUNS = {
    "track_video": _track_video,
    "online_camera": _online_camera,
    "online_camera_onnx": _online_camera_onnx,
    "edit_region": _edit_region,
    "sample_video": _sample_video,
    "evaluate": _evaluate,
    "convert_checkpoint": _convert_checkpoint,
    "benchmark": _benchmark,
    "train_small": _train_small,
    "calibrate_threshold": _calibrate_threshold,
}


@pytest.mark.parametrize("name", SCRIPTS)
def test_runs_on_generated_media(name, tmp_path, sample, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # nothing lands in the repository
    scratch = tmp_path / "system-tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))  # where mkdtemp() would leave things
    threads = torch.get_num_threads()  # scripts are entry points and may set it
    try:
        RUNS[name](tmp_path, sample, capsys)
    finally:
        torch.set_num_threads(threads)
    # torch keeps its compiler cache there on purpose; anything else is a leftover
    left = [p.name for p in scratch.iterdir() if not p.name.startswith("torchinductor_")]
    assert not left, f"{name} left temporary files behind: {left}"


def test_online_camera_without_a_camera_says_so_in_its_own_words(tmp_path, capfd):
    import argparse

    args = argparse.Namespace(camera=7, video=None)  # no machine of the suite has camera 7
    capture = _load("online_camera").open_stream(args, tmp_path)
    capture.release()
    out, err = capfd.readouterr()
    assert "no camera 7: reading the generated sample clip instead" in out
    assert "WARN" not in err and "libavdevice" not in err  # OpenCV's own lines are kept quiet
