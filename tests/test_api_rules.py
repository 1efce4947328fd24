"""One copy of each rule: the stream and the predictor check queries alike, and the
evaluation's both-ways tracking is the predictor's backward tracking."""

from __future__ import annotations

import re

import numpy as np
import pytest

from taptr.api.online import OnlineTracker
from taptr.eval.trackers import track_both_ways
from tests.helpers import float64_tiny_predictor, noise_video


@pytest.fixture(scope="module")
def predictor():
    return float64_tiny_predictor()


BAD_QUERIES = [
    [["a", "b", "c"]],
    [[0, 1]],
    [[0, np.nan, 1]],
    [[0, np.inf, 1]],
    [[0.5, 1, 1]],
    [[-1, 1, 1]],
    [[6, 1, 1]],
    [[0, 56, 1]],
    [[0, 1, -0.6]],
    np.zeros((2, 1, 3)),
    [[1 + 2j, 1, 1]],
    np.ones((1, 3), dtype=bool),
]


@pytest.mark.parametrize("queries", BAD_QUERIES)
def test_stream_and_predictor_reject_bad_queries_alike(predictor, queries):
    video = noise_video(6)
    with pytest.raises(ValueError) as offline:
        predictor.track(video, queries)
    online = OnlineTracker(predictor)
    state = online.start(num_frames=6, frame_size=(40, 56))
    with pytest.raises(ValueError, match=re.escape(str(offline.value))):
        online.add_queries(state, queries)


def test_stream_and_predictor_share_the_point_limit(predictor, monkeypatch):
    monkeypatch.setenv("TAPTR_MAX_POINTS", "2")
    queries = np.array([[0, 1, 1], [1, 2, 2], [2, 3, 3]], np.float32)
    with pytest.raises(ValueError) as offline:
        predictor.track(noise_video(6), queries)
    online = OnlineTracker(predictor)
    with pytest.raises(ValueError, match=re.escape(str(offline.value))):
        online.add_queries(online.start(num_frames=6, frame_size=(40, 56)), queries)


def test_eval_both_ways_equals_predictor_backward(predictor):
    video = noise_video(13, seed=4)
    queries = np.array([[0, 10, 20], [5, 55, 39], [12, 5.5, 5], [7, 30, 12.25]], np.float64)

    def forward_only(frames: np.ndarray, pass_queries: np.ndarray):
        result = predictor.track(frames, pass_queries)
        return result.tracks[0].numpy(), result.visibility[0].numpy()

    tracks, visible = track_both_ways(forward_only, video, queries)
    expected = predictor.track(video, queries, backward=True)
    np.testing.assert_allclose(tracks, expected.tracks[0].numpy(), atol=1e-5, rtol=0)
    np.testing.assert_array_equal(visible, expected.visibility[0].numpy())
    # the frames before the later queries really come from a reversed pass
    forward = predictor.track(video, queries)
    assert not np.allclose(tracks[:5, 1], forward.tracks[0, :5, 1].numpy())
