"""``taptr track``: streamed videos, several videos per run, resuming, and torchrun sharding."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import taptr
from taptr.cli.common.videos import expand_videos, result_folders
from taptr.cli.main import main
from taptr.io.tracks import load_tracks_npz
from taptr.io.video import read_video, write_video
from tests.helpers import run_torchrun

QUERIES = "0,16,22;3,30.5,20;5,50,10"


def _frames(count: int, shift: int) -> np.ndarray:
    frames = np.full((count, 48, 64, 3), 40, np.uint8)
    for t in range(count):
        frames[t, 16:28, 4 + shift * t : 16 + shift * t] = (230, 200, 40)
    return frames


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    folder = tmp_path_factory.mktemp("clips")
    for name, count, shift in (("a", 14, 2), ("b", 10, 3), ("c", 9, 1)):
        write_video(folder / f"{name}.mp4", _frames(count, shift), fps=10)
    return folder


@pytest.fixture(scope="module")
def checkpoint(tiny_checkpoint):
    return tiny_checkpoint


def test_streamed_tracks_equal_the_predictor(clips, checkpoint, tmp_path, capsys):
    out = tmp_path / "one"
    args = ["track", str(clips / "a.mp4"), "--points", QUERIES, "--checkpoint", str(checkpoint)]
    assert main([*args, "--out", str(out), "--trajectories"]) == 0
    saved = load_tracks_npz(out / "tracks.npz")
    predictor = taptr.Predictor.from_pretrained(checkpoint, device="cpu")
    expected = predictor.track(read_video(clips / "a.mp4"), saved.queries)
    # float32 noise only: chunks of 4 frames are encoded where the predictor encodes windows
    # (tests/test_streaming.py shows equality to 1e-6 in float64)
    np.testing.assert_allclose(saved.tracks, expected.tracks[0].numpy(), atol=5e-3, rtol=0)
    np.testing.assert_array_equal(saved.visibility, expected.visibility[0].numpy())
    assert saved.metadata["context_points"] == 6
    assert saved.metadata["model"] == str(checkpoint)
    assert {p.name for p in out.iterdir()} >= {"overlay.mp4", "tracks.csv", "trajectories.png"}
    assert len(read_video(out / "overlay.mp4")) == 14
    assert "tracked 3 points through 14 frames" in capsys.readouterr().out


def test_several_videos_one_folder_each_and_a_rerun_skips_them(clips, checkpoint, tmp_path, capsys):
    out = tmp_path / "many"
    args = ["track", str(clips), "--points", QUERIES, "--checkpoint", str(checkpoint)]
    assert main([*args, "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["a", "b", "c"]
    assert load_tracks_npz(out / "b" / "tracks.npz").tracks.shape == (10, 3, 2)
    assert "3 videos: 3 tracked, 0 already done, 0 failed" in capsys.readouterr().out
    (out / "c" / "overlay.mp4").unlink()  # as a crash before the end would leave it
    assert main([*args, "--out", str(out)]) == 0
    assert "3 videos: 1 tracked, 2 already done, 0 failed" in capsys.readouterr().out


def test_a_rerun_with_other_settings_tracks_again_and_overwrite_forces_it(
    clips, checkpoint, tmp_path, capsys
):
    out = tmp_path / "runs"
    videos = [str(clips / "b.mp4"), str(clips / "c.mp4")]
    base = ["track", *videos, "--max-frames", "5", "--checkpoint", str(checkpoint)]
    base += ["--out", str(out)]

    def summary(extra: list[str]) -> str:
        assert main([*base, *extra]) == 0
        return capsys.readouterr().out

    assert "2 videos: 2 tracked, 0 already done" in summary(["--grid", "2"])
    settings = json.loads((out / "b" / "settings.json").read_text())
    assert settings["queries"] == {"grid": 2, "query_frame": 0}
    assert settings["model"] == str(checkpoint) and settings["model_sha256"]
    assert "2 videos: 0 tracked, 2 already done" in summary(["--grid", "2"])
    printed = summary(["--grid", "3"])  # other queries: the old results are stale
    assert "2 videos: 2 tracked, 0 already done" in printed
    assert "was made with other settings; tracking it again" in printed
    assert load_tracks_npz(out / "c" / "tracks.npz").tracks.shape == (5, 9, 2)
    assert "2 tracked" in summary(["--grid", "3", "--backward"])
    assert load_tracks_npz(out / "c" / "tracks.npz").metadata["backward"] is True
    assert "0 tracked, 2 already done" in summary(["--grid", "3", "--backward"])
    assert "2 tracked, 0 already done" in summary(["--grid", "3", "--backward", "--overwrite"])
    (out / "b" / "settings.json").unlink()  # a folder from a taptr that did not record them
    assert "1 tracked, 1 already done" in summary(["--grid", "3", "--backward"])


def test_the_done_line_lists_every_file_and_counts_in_words(clips, checkpoint, tmp_path, capsys):
    out = tmp_path / "one"
    args = ["track", str(clips / "c.mp4"), "--points", "0,16,22", "--max-frames", "1"]
    assert main([*args, "--trajectories", "--checkpoint", str(checkpoint), "--out", str(out)]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert line.startswith("tracked 1 point through 1 frame; wrote ")
    written = line.split("; wrote ")[1].split(", ")
    assert sorted(Path(name).name for name in written) == sorted(p.name for p in out.iterdir())
    assert "trajectories.png" in line and "settings.json" in line


def test_a_failing_video_does_not_stop_the_others(clips, checkpoint, tmp_path, capsys):
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"not a video")
    args = ["track", str(clips / "b.mp4"), str(broken), "--grid", "2"]
    assert main([*args, "--checkpoint", str(checkpoint), "--out", str(tmp_path / "o")]) == 2
    out = capsys.readouterr().out
    assert "2 videos: 1 tracked, 0 already done, 1 failed" in out and "broken.mp4: failed" in out


def test_expanding_globs_folders_and_names(clips, tmp_path):
    assert [p.name for p in expand_videos([str(clips / "*.mp4")])] == ["a.mp4", "b.mp4", "c.mp4"]
    assert expand_videos([str(clips), str(clips / "a.mp4")]) == sorted(clips.glob("*.mp4"))
    with pytest.raises(FileNotFoundError, match="no video matches"):
        expand_videos([str(clips / "*.webm")])
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "0001.png").write_bytes(b"")
    assert expand_videos([str(frames)]) == [frames]  # an image folder is one video
    twins = [tmp_path / "x" / "a.mp4", tmp_path / "y" / "a.mp4", tmp_path / "b.mp4"]
    assert [p.name for p in result_folders(twins, tmp_path / "o")] == ["x-a", "y-a", "b"]
    assert result_folders(twins[:1], tmp_path / "o") == [tmp_path / "o"]


def test_two_processes_write_the_same_files_as_one(clips, checkpoint, tmp_path):
    args = ["track", str(clips), "--points", QUERIES, "--checkpoint", str(checkpoint)]
    # the single process runs as the two do (a fresh process, one thread): in this test
    # process the thread count and what earlier tests left behind could change rounding
    alone = run_torchrun([*args, "--device", "cpu", "--out", str(tmp_path / "one")], processes=1)
    assert alone.returncode == 0, alone.stderr[-2000:]
    done = run_torchrun([*args, "--device", "cpu", "--out", str(tmp_path / "two")])
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.count("3 videos: 3 tracked") == 1  # one summary, from rank 0
    for name in ("a", "b", "c"):
        one = load_tracks_npz(tmp_path / "one" / name / "tracks.npz")
        two = load_tracks_npz(tmp_path / "two" / name / "tracks.npz")
        np.testing.assert_array_equal(one.tracks, two.tracks)
        np.testing.assert_array_equal(one.visibility, two.visibility)


def test_an_accepted_truncated_video_is_tracked_in_memory_after_a_warning(
    checkpoint, tmp_path, caplog
):
    import logging

    import av

    rng = np.random.default_rng(0)
    path = write_video(tmp_path / "v.mp4", rng.integers(0, 256, (12, 48, 64, 3), np.uint8), 10)
    with av.open(str(path)) as container:
        cut = [p.pos for p in container.demux(container.streams.video[0]) if p.size][5]
    truncated = tmp_path / "truncated.mp4"
    truncated.write_bytes(path.read_bytes()[:cut])  # declares 12 frames, decodes 5
    args = ["track", str(truncated), "--grid", "2", "--checkpoint", str(checkpoint)]
    args.append("--accept-truncated")  # without it: an error (the next test)
    with caplog.at_level(logging.WARNING), pytest.warns(UserWarning, match="declares 12"):
        assert main([*args, "--out", str(tmp_path / "o")]) == 0
    assert "tracking it in memory instead" in caplog.text
    assert load_tracks_npz(tmp_path / "o" / "tracks.npz").tracks.shape == (5, 4, 2)


def test_backward_tracking_streams_and_equals_the_predictor(
    clips, checkpoint, tmp_path, monkeypatch
):
    import taptr.io.video as video_io

    def no_whole_video(*args, **kwargs):
        raise AssertionError("--backward read the whole video into memory")

    monkeypatch.setattr(video_io, "read_video", no_whole_video)
    out = tmp_path / "both"
    args = ["track", str(clips / "a.mp4"), "--points", QUERIES, "--checkpoint", str(checkpoint)]
    assert main([*args, "--backward", "--out", str(out), "--trajectories"]) == 0
    monkeypatch.undo()
    saved = load_tracks_npz(out / "tracks.npz")
    predictor = taptr.Predictor.from_pretrained(checkpoint, device="cpu")
    expected = predictor.track(read_video(clips / "a.mp4"), saved.queries, backward=True)
    np.testing.assert_allclose(saved.tracks, expected.tracks[0].numpy(), atol=5e-3, rtol=0)
    np.testing.assert_array_equal(saved.visibility, expected.visibility[0].numpy())
    assert saved.metadata["backward"] is True
    assert len(read_video(out / "overlay.mp4")) == 14


@pytest.mark.parametrize("query_frame", [0, 6])
def test_edit_streams_and_equals_the_in_memory_edit(clips, checkpoint, tmp_path, query_frame):
    import argparse

    from taptr.api.regions import sample_region_queries
    from taptr.apps.editing import overlay_region
    from taptr.cli.edit import _edited_frames

    mask = np.zeros((48, 64), bool)
    mask[14:30, 2:22] = True
    overlay = np.zeros((8, 8, 3), np.uint8)
    overlay[..., 2] = 255
    video_path = clips / "a.mp4"
    queries = sample_region_queries(mask, query_frame, stride=3)
    predictor = taptr.Predictor.from_pretrained(checkpoint, device="cpu")
    args = argparse.Namespace(video=str(video_path), max_frames=None, opacity=0.8)
    streamed = np.stack(list(_edited_frames(args, predictor, queries, mask, overlay, 14)))
    video = read_video(video_path)
    result = predictor.track(video, queries, backward=True)
    tracks, visibility = result.tracks[0].numpy(), result.visibility[0].numpy()
    expected = overlay_region(video, overlay, mask, tracks, visibility, query_frame, opacity=0.8)
    assert streamed.shape == expected.shape == (14, 48, 64, 3)
    difference = np.abs(streamed.astype(int) - expected.astype(int))
    assert difference.mean() < 0.05 and np.percentile(difference, 99) <= 2  # float32 noise
    pasted = streamed[query_frame].astype(int) - video[query_frame].astype(int)
    assert np.abs(pasted).max() > 100


def test_a_video_cut_short_is_an_error_unless_accepted(checkpoint, tmp_path, capsys):
    from tests.helpers import write_truncated_clip

    decoded = write_truncated_clip(tmp_path / "cut.mp4")
    args = ["track", str(tmp_path / "cut.mp4"), "--grid", "2", "--checkpoint", str(checkpoint)]
    assert main([*args, "--out", str(tmp_path / "refused")]) == 2
    error = capsys.readouterr().err
    assert f"decoded {decoded} of the 24 frames its container declares" in error
    assert "--accept-truncated" in error and not (tmp_path / "refused" / "tracks.npz").exists()
    assert main([*args, "--out", str(tmp_path / "kept"), "--accept-truncated"]) == 0
    assert load_tracks_npz(tmp_path / "kept" / "tracks.npz").tracks.shape[0] == decoded
