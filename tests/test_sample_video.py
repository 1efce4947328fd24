"""The procedural sample clip: determinism, and ground truth that matches the pixels."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from taptr.data.sample_video import make_sample_clip, write_sample_video
from taptr.io.video import read_video, video_info


@pytest.fixture(scope="module")
def clip():
    return make_sample_clip()


def _sample(frame: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) bilinear colours at (x, y) pixel positions (pixel centres at integers)."""
    xs = np.ascontiguousarray(points[:, None, 0], np.float32)
    ys = np.ascontiguousarray(points[:, None, 1], np.float32)
    return cv2.remap(frame, xs, ys, cv2.INTER_LINEAR)[:, 0].astype(float)


def _background_queries(clip, frame: int) -> np.ndarray:
    """Grid queries on ``frame`` well clear of the disc and the image border."""
    grid = np.stack(np.meshgrid(np.arange(20, 236, 9), np.arange(20, 236, 9)), -1).reshape(-1, 2)
    far = np.linalg.norm(grid - clip.disc_centers()[frame], axis=1) > clip.disc_radius + 4
    points = grid[far].astype(np.float32)
    return np.column_stack([np.full(len(points), frame, np.float32), points])


def test_clip_is_deterministic_and_seeded(clip):
    assert clip.video.shape == (48, 256, 256, 3) and clip.video.dtype == np.uint8
    assert clip.camera.shape == clip.disc.shape == (48, 3, 3) and clip.fps == 24
    small = make_sample_clip(num_frames=3, height=40, width=56)
    np.testing.assert_array_equal(
        small.video, make_sample_clip(num_frames=3, height=40, width=56).video
    )
    assert small.video.shape == (3, 40, 56, 3)
    assert not np.array_equal(
        small.video, make_sample_clip(num_frames=3, height=40, width=56, seed=1).video
    )
    assert (
        np.abs(np.diff(clip.video.astype(int), axis=0)).mean(axis=(1, 2, 3)) > 1
    ).all()  # it moves


def test_background_tracks_match_the_pixels(clip):
    queries = _background_queries(clip, 0)
    tracks, visible = clip.track(queries)
    np.testing.assert_allclose(tracks[0], queries[:, 1:], atol=1e-4)
    reference = _sample(clip.video[0], queries[:, 1:])
    for t in (12, 30, 47):
        seen = visible[t]
        error = np.abs(_sample(clip.video[t], tracks[t, seen]) - reference[seen]).mean()
        shifted = np.abs(_sample(clip.video[t], tracks[t, seen] + 1.5) - reference[seen]).mean()
        assert error < 8 and shifted > 2 * error


def test_disc_points_move_with_the_disc_and_occlude_the_background(clip):
    center = clip.disc_centers()[10]
    on_disc = np.array([[10, *(center + [5.0, -3.0])]], np.float32)
    tracks, visible = clip.track(on_disc)
    offsets = tracks[:, 0] - clip.disc_centers()
    np.testing.assert_allclose(offsets[10], [5.0, -3.0], atol=1e-3)
    np.testing.assert_allclose(np.linalg.norm(offsets, axis=1), np.hypot(5, 3), atol=1e-3)
    assert np.linalg.norm(offsets[30] - offsets[10]) > 1  # the disc rolls
    colour = _sample(clip.video[10], on_disc[:, 1:])
    assert np.abs(_sample(clip.video[20], tracks[20]) - colour).mean() < 8
    assert visible[10:40, 0].all()
    # The background point under the disc's centre on frame 30, queried on frame 0.
    to_frame_0 = clip.camera[0] @ np.linalg.inv(clip.camera[30])
    start = (to_frame_0 @ [*clip.disc_centers()[30], 1.0])[:2]
    tracks, visible = clip.track(np.array([[0, *start]], np.float32))
    np.testing.assert_allclose(tracks[30, 0], clip.disc_centers()[30], atol=1e-3)
    assert visible[0, 0] and not visible[30, 0]
    distance = np.linalg.norm(tracks[:, 0] - clip.disc_centers(), axis=1)
    np.testing.assert_array_equal(visible[:, 0], distance > clip.disc_radius)


def test_points_leaving_the_frame_are_invisible(clip):
    corner = np.array([[0, 1.0, 1.0], [47, 254.0, 1.0]], np.float32)  # the camera zooms in
    tracks, visible = clip.track(corner)
    assert visible[0, 0] and not visible[47, 0] and (tracks[47, 0] < -0.5).any()
    assert visible[47, 1] and tracks.shape == (48, 2, 2)
    with pytest.raises(ValueError, match="query frames"):
        clip.track(np.array([[48, 1.0, 1.0]]))


def test_write_sample_video(tmp_path, clip):
    path = write_sample_video(tmp_path / "sample.mp4")
    info = video_info(path)
    assert (info.num_frames, info.fps, info.height, info.width) == (48, 24.0, 256, 256)
    decoded = read_video(path, stride=20)
    assert np.abs(decoded.astype(int) - clip.video[::20]).mean() < 8  # yuv420p chroma on edges


def test_the_command_varies_length_size_and_seed(tmp_path, capsys):
    from taptr.cli.main import main

    path = tmp_path / "short.mp4"
    assert (
        main(["sample-video", str(path), "--frames", "5", "--size", "40", "56", "--seed", "3"]) == 0
    )
    info = video_info(path)
    assert (info.num_frames, info.height, info.width, info.fps) == (5, 40, 56, 24.0)
    expected = make_sample_clip(num_frames=5, height=40, width=56, seed=3).video
    assert np.abs(read_video(path).astype(int) - expected).mean() < 8  # the same frames, encoded
    for argv, message in (
        (["--frames", "1"], "--frames must lie in [2, 100000], got 1"),
        (["--size", "8", "64"], "--size 8 64: each side must lie in [16, 4096]"),
    ):
        assert main(["sample-video", str(tmp_path / "x.mp4"), *argv]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "x.mp4").exists()
