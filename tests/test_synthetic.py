"""Procedural videos: deterministic, tracks follow the content, real occlusions."""

from __future__ import annotations

import numpy as np
import pytest

from taptr.cli.main import main as cli_main
from taptr.data.kubric import list_sequences, read_sequence
from taptr.data.synthetic import SyntheticConfig, make_video

CONFIG = SyntheticConfig(height=96, width=128, num_frames=12, num_points=400, objects=(3, 4))


@pytest.fixture(scope="module")
def video():
    return make_video(np.random.default_rng(7), CONFIG)


def test_shapes_and_determinism(video):
    assert video.video.shape == (12, 96, 128, 3) and video.video.dtype == np.uint8
    assert video.tracks.shape == (12, 400, 2) and video.visible.shape == (12, 400)
    again = make_video(np.random.default_rng(7), CONFIG)
    np.testing.assert_array_equal(again.video, video.video)
    np.testing.assert_array_equal(again.tracks, video.tracks)
    other = make_video(np.random.default_rng(8), CONFIG)
    assert not np.array_equal(other.video, video.video)


def test_every_point_is_visible_where_it_was_sampled(video):
    assert video.visible.any(axis=0).all()
    assert (video.visible[0] | video.visible[6]).mean() > 0.5  # many on the first/middle frame


def test_tracks_follow_the_content(video):
    """The colour under a point barely changes between two frames where it is visible,
    while the colour under unrelated points does."""
    frames = np.arange(12)
    rows = np.round(video.tracks[..., 1]).clip(0, 95).astype(int)
    cols = np.round(video.tracks[..., 0]).clip(0, 127).astype(int)
    colours = video.video[frames[:, None], rows, cols].astype(float)  # (T, N, 3)
    first = video.visible.argmax(0)
    same, other = [], []
    for t in range(1, 12):
        both = video.visible[t] & (first < t)
        matched = colours[t, both] - colours[first[both], np.flatnonzero(both)]
        same.append(np.abs(matched).mean(1))
        shuffled = np.roll(colours[t, both], 1, axis=0) - colours[first[both], np.flatnonzero(both)]
        other.append(np.abs(shuffled).mean(1))
    same, other = np.concatenate(same), np.concatenate(other)
    assert same.size > 500
    assert np.median(same) < 0.2 * np.median(other)


def test_occlusion_and_leaving_the_image(video):
    x, y = video.tracks[..., 0], video.tracks[..., 1]
    inside = (x >= 0) & (x <= 127) & (y >= 0) & (y <= 95)
    assert not (video.visible & ~inside).any()  # outside is never visible
    assert (~inside).any()  # some points leave the image
    assert (~video.visible & inside).sum() > 50  # real occlusions inside the image


def test_make_synthetic_command_writes_the_kubric_layout(tmp_path, capsys):
    args = ["make-synthetic", "--out", str(tmp_path), "--videos", "2", "--size", "32", "48"]
    assert cli_main(args + ["--frames", "5", "--points", "30", "--seed", "3"]) == 0
    assert "wrote 2 videos" in capsys.readouterr().out
    folders = list_sequences(tmp_path)
    assert [f.name for f in folders] == ["00000", "00001"]
    sample = read_sequence(folders[1])
    expected = make_video(
        np.random.default_rng((3, 1)),
        SyntheticConfig(height=32, width=48, num_frames=5, num_points=30),
    )
    np.testing.assert_array_equal(sample.video, expected.video)
    np.testing.assert_allclose(sample.tracks, expected.tracks)
    np.testing.assert_array_equal(sample.visible, expected.visible)
    assert cli_main(["make-synthetic", "--out", str(tmp_path), "--videos", "0"]) == 2
