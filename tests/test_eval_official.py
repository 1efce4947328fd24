"""The official TAPTR evaluation recipe: query padding, scaling, passes and fusion."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from taptr.eval.official_protocol import OfficialTAPTR, official_padding
from taptr.eval.protocols import OfficialProtocol, StandardProtocol
from taptr.eval.query_sampling import sample_queries
from tests.test_tapvid_fabricated import make_clip

pytestmark = pytest.mark.usefixtures("one_thread")


def test_padding_follows_the_seed0_recipe():
    real = np.array([[10.5, 20.25], [100.0, 3.0], [30.0, 240.0]])
    padding = official_padding(real, num_frames=24)
    assert padding.positions.shape == (797, 2) and padding.start_frames.shape == (797,)
    # the list starts with the real frame-0 positions, and all of it is returned
    np.testing.assert_array_equal(padding.positions[:3], real)
    drawn = padding.positions[3:]
    np.testing.assert_array_equal(drawn, drawn.round())
    assert drawn.min() >= 16 and drawn.max() <= 239
    # the first draw of numpy's legacy generator seeded with 0 comes first
    np.testing.assert_array_equal(drawn[0], np.random.RandomState(0).randint(16, 240, size=2))
    gaps = np.linalg.norm(padding.positions[:, None] - padding.positions[None], axis=-1)
    assert gaps[~np.eye(797, dtype=bool)].min() >= 1
    assert padding.start_frames.min() >= 0 and padding.start_frames.max() < 12


def test_padding_is_deterministic_and_leaves_numpy_global_state_alone():
    np.random.seed(123)
    expected_next = np.random.RandomState(123).rand()
    first = official_padding(np.zeros((0, 2)), 20, num_queries=50)
    assert np.random.rand() == expected_next
    second = official_padding(np.zeros((0, 2)), 20, num_queries=50)
    np.testing.assert_array_equal(first.positions, second.positions)
    np.testing.assert_array_equal(first.start_frames, second.start_frames)


def test_padding_with_many_real_points_returns_the_last_real_positions():
    real = np.stack([np.arange(500.0), np.arange(500.0)], axis=1)
    padding = official_padding(real, 30)
    np.testing.assert_array_equal(padding.positions, real[-300:])
    np.testing.assert_array_equal(
        padding.start_frames, np.random.RandomState(0).randint(0, 12, 300)
    )
    assert len(official_padding(np.zeros((800, 2)), 30).positions) == 0


def test_padding_of_short_videos_keeps_every_point_visible_somewhere():
    padding = official_padding(np.zeros((0, 2)), num_frames=5)
    assert padding.start_frames.max() == 4  # capped at T − 1 instead of failing
    long = official_padding(np.zeros((0, 2)), num_frames=12)
    assert long.start_frames.max() == 11


def test_official_scaling_is_raster_times_255():
    sample = make_clip(8)
    official = OfficialProtocol(None).prepare(sample)
    standard = StandardProtocol(None).prepare(sample)
    raster = (sample.tracks + 0.5) / 64
    np.testing.assert_allclose(official.tracks, raster * 255, atol=1e-4)
    np.testing.assert_allclose(standard.tracks, raster * 256 - 0.5, atol=1e-4)
    assert official.video.shape == (8, 256, 256, 3)


@pytest.fixture(scope="module")
def official_tiny():
    from taptr import build_model

    torch.manual_seed(0)
    return OfficialTAPTR(build_model("tiny"), num_queries=24)


def test_first_mode_pads_and_returns_the_real_points(official_tiny):
    clip = OfficialProtocol(None).prepare(make_clip(8))  # shorter than 12 frames
    points = sample_queries(clip.tracks, clip.visible, "first")
    tracks, visible = official_tiny.predict(clip.video, points, "first")
    assert tracks.shape == (8, len(points.queries), 2) and visible.shape == tracks.shape[:2]
    frames = points.queries[:, 0].astype(int)
    # the start frame is never updated: each point is at its query there, visible
    n = np.arange(len(frames))
    np.testing.assert_allclose(tracks[frames, n], points.queries[:, 1:], atol=1e-3)
    # the padding takes part: other distractors change the real points' tracks
    wider = OfficialTAPTR(official_tiny.model, num_queries=40)
    other, _ = wider.predict(clip.video, points, "first")
    assert not np.allclose(other, tracks, atol=1e-4)


def test_strided_mode_fuses_a_forward_and_a_reversed_pass_per_query_frame(official_tiny):
    clip = OfficialProtocol(None).prepare(make_clip(9))
    points = sample_queries(clip.tracks, clip.visible, "strided")
    tracks, visible = official_tiny.predict(clip.video, points, "strided")
    assert tracks.shape == (9, len(points.queries), 2)
    # rebuild the frame-5 group's two passes by hand
    group = np.flatnonzero(points.queries[:, 0] == 5)
    padding = official_padding(points.tracks[0, group], 9, 24)
    padded = np.concatenate(
        [points.queries[group], np.c_[np.full(len(padding.positions), 5), padding.positions]]
    )
    labels = np.r_[np.ones(len(group), bool), padding.start_frames <= 5]
    forward, forward_visible = official_tiny._pass(clip.video, padded, labels)
    flipped = padded.copy()
    flipped[:, 0] = 8 - 5
    backward, backward_visible = official_tiny._pass(clip.video[::-1].copy(), flipped, labels)
    np.testing.assert_allclose(tracks[5:, group], forward[5:, : len(group)], atol=1e-5)
    np.testing.assert_allclose(tracks[:5, group], backward[::-1][:5, : len(group)], atol=1e-5)
    np.testing.assert_array_equal(visible[5:, group], forward_visible[5:, : len(group)])
    np.testing.assert_array_equal(visible[:5, group], backward_visible[::-1][:5, : len(group)])
