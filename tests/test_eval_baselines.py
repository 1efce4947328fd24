"""The static and Lucas–Kanade baselines on a clip with known motion."""

from __future__ import annotations

import numpy as np

from taptr.eval.baselines import LucasKanadeTracker, StaticTracker
from taptr.eval.protocols import resize_video
from tests.test_tapvid_fabricated import make_clip


def _queries(sample, frame=0, scale=1.0):
    """(N, 3) (t, x, y) queries on ``frame``, in a video ``scale`` times the clip's size."""
    positions = (sample.tracks[frame] + 0.5) * scale - 0.5
    return np.concatenate([np.full((len(positions), 1), frame), positions], axis=1)


def test_static_points_stay_at_their_query_and_are_visible():
    sample = make_clip(8)
    queries = _queries(sample, frame=3)
    tracks, visible = StaticTracker().track(sample.video, queries)
    assert tracks.shape == (8, 12, 2) and visible.shape == (8, 12)
    np.testing.assert_array_equal(tracks, np.broadcast_to(queries[:, 1:], (8, 12, 2)))
    assert visible.all()


def test_lk_follows_the_texture():
    sample = make_clip(12, occluder=False)
    tracks, visible = LucasKanadeTracker().track(sample.video, _queries(sample))
    np.testing.assert_allclose(tracks, sample.tracks, atol=0.05)
    assert visible.all()


def test_lk_holds_the_query_position_before_the_query_frame():
    sample = make_clip(12, occluder=False)
    queries = _queries(sample, frame=4)
    tracks, _ = LucasKanadeTracker().track(sample.video, queries)
    np.testing.assert_array_equal(tracks[:5], np.broadcast_to(queries[:, 1:], (5, 12, 2)))
    np.testing.assert_allclose(tracks[4:], sample.tracks[4:], atol=0.05)


def test_lk_forward_backward_check_flags_lost_points():
    """On a cut to unrelated content the flow does not come back: the points are occluded."""
    sample = make_clip(12, occluder=False)
    video = resize_video(sample.video).copy()  # at 256 × 256, as the benchmark runs it
    video[6:] = resize_video(make_clip(6, seed=7, occluder=False).video)
    _, visible = LucasKanadeTracker().track(video, _queries(sample, scale=4))
    assert visible[:6].all()
    assert (~visible[6]).mean() > 0.8  # after the cut LK follows the new texture again
