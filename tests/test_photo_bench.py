"""The real-photo benchmark: exact tracks, TAP-Vid DAVIS format, read back by ``taptr eval``."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from taptr.cli.main import main as cli_main
from taptr.data.photo_bench import PhotoBenchConfig, make_photo_video, write_photo_bench
from taptr.data.tapvid import iter_tapvid
from tests.photo_checks import colour_drift, colours_under, fabricated_photo

CONFIG = PhotoBenchConfig(height=96, width=112, num_frames=10, num_points=120)


PHOTOS = [fabricated_photo(seed, 150, 170, cell=6) for seed in (0, 1)]


@pytest.fixture(scope="module")
def video():
    return make_photo_video(np.random.default_rng(3), PHOTOS, CONFIG)


def test_shapes_and_determinism(video):
    assert video.video.shape == (10, 96, 112, 3) and video.video.dtype == np.uint8
    assert video.tracks.shape == (10, 120, 2) and video.visible.shape == (10, 120)
    again = make_photo_video(np.random.default_rng(3), PHOTOS, CONFIG)
    np.testing.assert_array_equal(again.video, video.video)
    np.testing.assert_array_equal(again.tracks, video.tracks)
    with pytest.raises(ValueError, match="photograph"):
        make_photo_video(np.random.default_rng(3), [], CONFIG)


def test_points_lie_on_photographs_and_follow_them(video):
    colours = colours_under(video.video, video.tracks)  # (T, N, 3)
    # points are never sampled on the occluder: where visible, they show the photograph
    # (at the occluder's anti-aliased edge less than half of its colour shows)
    blue = colours[..., 2][video.visible]
    assert (blue <= 128).all() and (blue == 0).mean() > 0.9
    same, other = colour_drift(colours, video.visible)
    assert same.size > 200
    assert np.median(same) < 0.3 * np.median(other)


def test_visibility_is_exact(video):
    assert video.visible.any(axis=0).all()  # visible where it was sampled
    x, y = video.tracks[..., 0], video.tracks[..., 1]
    inside = (x >= 0) & (x <= 111) & (y >= 0) & (y <= 95)
    assert not (video.visible & ~inside).any()
    # the camera and the layers really move
    moved = np.linalg.norm(video.tracks[-1] - video.tracks[0], axis=-1)
    assert np.median(moved) > 3


def test_occluder_hides_points_inside_the_frame():
    hidden = 0
    for seed in range(4):
        sample = make_photo_video(np.random.default_rng(seed), PHOTOS, CONFIG)
        x, y = sample.tracks[..., 0], sample.tracks[..., 1]
        inside = (x >= 0) & (x <= 111) & (y >= 0) & (y <= 95)
        hidden += int((inside & ~sample.visible).sum())
    assert hidden > 50


def test_written_pickle_reads_back_as_davis(tmp_path):
    path = write_photo_bench(tmp_path / "bench.pkl", 2, PHOTOS, CONFIG, seed=4)
    videos = list(iter_tapvid("davis", path))
    assert [v.name for v in videos] == ["photo_000", "photo_001"]
    expected = make_photo_video(np.random.default_rng((4, 1)), PHOTOS, CONFIG)
    loaded = videos[1].load()
    np.testing.assert_array_equal(loaded.video, expected.video)
    np.testing.assert_allclose(loaded.tracks, expected.tracks, atol=1e-3)
    np.testing.assert_array_equal(loaded.visible, expected.visible)
    with pytest.raises(ValueError):
        write_photo_bench(tmp_path / "none.pkl", 0, PHOTOS, CONFIG)


def test_cli_make_and_evaluate(tmp_path, capsys):
    folder = tmp_path / "photos"
    folder.mkdir()
    for index, photo in enumerate(PHOTOS):
        cv2.imwrite(str(folder / f"{index}.png"), photo[..., ::-1])
    out = tmp_path / "bench.pkl"
    args = ["make-photo-bench", "--out", str(out), "--videos", "2", "--size", "64", "64"]
    assert cli_main([*args, "--frames", "8", "--points", "40", "--photos", str(folder)]) == 0
    assert "from 2 photographs" in capsys.readouterr().out
    results = tmp_path / "static"
    argv = ["eval", "--dataset", "davis", "--root", str(out), "--tracker", "static"]
    assert cli_main([*argv, "--out", str(results)]) == 0
    report = json.loads((results / "results.json").read_text())
    assert [v["name"] for v in report["videos"]] == ["photo_000", "photo_001"]
    assert 0 <= report["mean"]["average_jaccard"] < 0.5  # the points do move
