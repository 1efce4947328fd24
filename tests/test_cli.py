"""The command line: help, track and edit on generated videos, one-line errors."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest

from taptr.cli.main import main
from taptr.io.tracks import load_tracks_csv, load_tracks_npz
from taptr.io.video import read_video, video_info, write_video


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """A 10-frame 48×64 video with a bright square moving right by 2 px per frame."""
    frames = np.full((10, 48, 64, 3), 40, np.uint8)
    for t in range(10):
        frames[t, 16:28, 10 + 2 * t : 22 + 2 * t] = (230, 200, 40)
    return write_video(tmp_path_factory.mktemp("clip") / "clip.mp4", frames, fps=10)


def test_help_lists_the_commands():
    out = subprocess.run(
        [sys.executable, "-m", "taptr.cli.main", "--help"], capture_output=True, text=True
    )
    assert out.returncode == 0
    for command in ("convert", "track", "edit", "sample-video"):
        assert command in out.stdout


def test_track_writes_tracks_csv_and_overlay(clip, tmp_path, capsys):
    out = tmp_path / "out"
    args = [
        "track",
        str(clip),
        "--points",
        "0,16,22;3,30.5,20",
        "--checkpoint",
        "tiny",
        "--out",
        str(out),
    ]
    assert main([*args, "--trajectories"]) == 0
    saved = load_tracks_npz(out / "tracks.npz")
    assert saved.tracks.shape == (10, 2, 2) and saved.visibility.shape == (10, 2)
    np.testing.assert_array_equal(saved.queries, [[0, 16, 22], [3, 30.5, 20]])
    assert saved.tracks[3, 1].tolist() == [30.5, 20.0]
    assert saved.metadata["num_frames"] == 10 and saved.metadata["width"] == 64
    tracks, visibility = load_tracks_csv(out / "tracks.csv")
    np.testing.assert_allclose(tracks, saved.tracks, atol=1e-4)
    np.testing.assert_array_equal(visibility, saved.visibility)
    assert len((out / "tracks.csv").read_text().strip().splitlines()) == 1 + 10 * 2
    info = video_info(out / "overlay.mp4")
    assert (info.num_frames, info.height, info.width) == (10, 48, 64)
    assert cv2.imread(str(out / "trajectories.png")).shape == (48, 64, 3)
    assert "tracked 2 points through 10 frames" in capsys.readouterr().out


def test_track_grid_and_mask(clip, tmp_path):
    assert (
        main(
            [
                "track",
                str(clip),
                "--grid",
                "3",
                "--checkpoint",
                "tiny",
                "--out",
                str(tmp_path / "g"),
            ]
        )
        == 0
    )
    assert load_tracks_npz(tmp_path / "g" / "tracks.npz").tracks.shape == (10, 9, 2)
    mask = np.zeros((48, 64), np.uint8)
    mask[16:28, 16:28] = 255
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    args = ["track", str(clip), "--mask", str(tmp_path / "mask.png"), "--query-frame", "3"]
    assert (
        main([*args, "--mask-stride", "4", "--checkpoint", "tiny", "--out", str(tmp_path / "m")])
        == 0
    )
    saved = load_tracks_npz(tmp_path / "m" / "tracks.npz")
    assert saved.tracks.shape[1] == 9 and (saved.queries[:, 0] == 3).all()


def test_track_points_file(clip, tmp_path):
    points = tmp_path / "points.csv"
    points.write_text("t,x,y\n0,16,22\n# a comment\n2, 40, 10\n")
    assert (
        main(
            [
                "track",
                str(clip),
                "--points-file",
                str(points),
                "--checkpoint",
                "tiny",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    assert load_tracks_npz(tmp_path / "tracks.npz").queries.shape == (2, 3)


def test_edit_pastes_the_overlay_on_the_query_frame(clip, tmp_path):
    mask = np.zeros((48, 64), np.uint8)
    mask[16:28, 14:26] = 255
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    cv2.imwrite(
        str(tmp_path / "logo.png"), np.full((8, 8, 3), (255, 0, 0), np.uint8)
    )  # blue in BGR
    out = tmp_path / "edited.mp4"
    args = [
        "edit",
        str(clip),
        "--mask",
        str(tmp_path / "mask.png"),
        "--overlay",
        str(tmp_path / "logo.png"),
    ]
    assert (
        main(
            [
                *args,
                "--query-frame",
                "2",
                "--stride",
                "3",
                "--checkpoint",
                "tiny",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    edited = read_video(out)
    assert edited.shape == (10, 48, 64, 3)
    # on the query frame the tracked points are the queries themselves: the overlay is exact
    inside = edited[2, 18:26, 16:24].reshape(-1, 3).mean(0)
    assert inside[2] > 150 and inside[0] < 100  # blue, where the clip is yellow


BAD = [
    (["track", "missing.mp4", "--grid", "2"], "not found"),
    (["track", "{clip}", "--points", "12,1,1"], r"outside \[0, 10\)"),
    (["track", "{clip}", "--points", "0,70,1"], "outside the 64x48 frame"),
    (["track", "{clip}", "--points", "0,nan,1"], "NaN"),
    (["track", "{clip}", "--points", "0,1"], "triples"),
    (["track", "{clip}", "--mask", "{small_mask}"], "the video is 64x48"),
    (["track", "{garbage}", "--grid", "2"], "garbage.mp4"),
    (["track", "{clip}", "--grid", "2", "--checkpoint", "{wrong_ckpt}"], "does not match"),
]


@pytest.mark.parametrize(("argv", "message"), BAD)
def test_bad_input_is_one_line_and_writes_nothing(clip, tmp_path, capsys, argv, message):
    import re

    import torch

    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((10, 10), np.uint8))
    (tmp_path / "garbage.mp4").write_bytes(b"\x00" * 100)
    from taptr import build_model
    from taptr.weights.checkpoint import checkpoint_dict

    bad = checkpoint_dict(build_model("tiny"))
    bad["model"].pop("encoder.level_embed")
    torch.save(bad, tmp_path / "wrong.pth")
    paths = {
        "clip": clip,
        "small_mask": tmp_path / "small.png",
        "garbage": tmp_path / "garbage.mp4",
        "wrong_ckpt": tmp_path / "wrong.pth",
    }
    argv = [a.format(**paths) for a in argv]
    if "--checkpoint" not in argv:
        argv += ["--checkpoint", "tiny"]
    out = tmp_path / "out"
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert re.search(message, err), err
    assert err.startswith("taptr track: error:") and "Traceback" not in err
    assert not out.exists()
