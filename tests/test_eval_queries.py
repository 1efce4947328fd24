"""Query sampling (first, strided) and the strided protocol for forward-in-time trackers."""

from __future__ import annotations

import numpy as np
import pytest

from taptr.eval.protocols import StandardProtocol, evaluate_video
from taptr.eval.query_sampling import sample_queries
from taptr.eval.trackers import run_tracker, track_both_ways
from tests.test_tapvid_fabricated import make_clip


def _toy_ground_truth():
    """Three tracks over 11 frames: visible from frame 2, never visible, visible 0–6."""
    tracks = np.arange(11 * 3 * 2, dtype=np.float32).reshape(11, 3, 2)
    visible = np.zeros((11, 3), dtype=bool)
    visible[2:, 0] = True
    visible[:7, 2] = True
    return tracks, visible


def test_first_queries_each_visible_track_on_its_first_visible_frame():
    tracks, visible = _toy_ground_truth()
    points = sample_queries(tracks, visible, "first")
    np.testing.assert_array_equal(points.queries[:, 0], [2, 0])
    np.testing.assert_array_equal(points.queries[:, 1:], [tracks[2, 0], tracks[0, 2]])
    np.testing.assert_array_equal(points.tracks, tracks[:, [0, 2]])
    np.testing.assert_array_equal(points.visible, visible[:, [0, 2]])


def test_strided_queries_every_fifth_frame_with_duplicated_tracks():
    tracks, visible = _toy_ground_truth()
    points = sample_queries(tracks, visible, "strided")
    # frame 0: track 2; frame 5: tracks 0 and 2; frame 10: track 0 — stride by stride
    np.testing.assert_array_equal(points.queries[:, 0], [0, 5, 5, 10])
    np.testing.assert_array_equal(
        points.queries[:, 1:], [tracks[0, 2], tracks[5, 0], tracks[5, 2], tracks[10, 0]]
    )
    np.testing.assert_array_equal(points.visible, visible[:, [2, 0, 2, 0]])
    with pytest.raises(ValueError, match="unknown query mode"):
        sample_queries(tracks, visible, "last")


class ForwardOracle:
    """Exact ground truth from each query frame on, nonsense before it (a causal tracker).

    It recognises the video it is given (the clip or the clip reversed in time) and finds
    each query's track by its position on the query frame.
    """

    def __init__(self, clip, bidirectional=False):
        self.clip = clip
        self.bidirectional = bidirectional
        self.calls = 0

    def track(self, video, queries):
        self.calls += 1
        if np.array_equal(video, self.clip.video):
            truth, shown = self.clip.tracks, self.clip.visible
        else:
            assert np.array_equal(video, self.clip.video[::-1])
            truth, shown = self.clip.tracks[::-1], self.clip.visible[::-1]
        frames = queries[:, 0].astype(int)
        distance = np.linalg.norm(truth[frames] - queries[:, None, 1:], axis=-1)  # (N, tracks)
        track_ids = distance.argmin(axis=1)
        tracks, visible = truth[:, track_ids].copy(), shown[:, track_ids].copy()
        before = np.arange(len(video))[:, None] < frames[None]
        tracks[before] += 100.0
        visible[before] = True
        return tracks, visible


def test_strided_with_an_exact_forward_tracker_scores_perfectly():
    sample = make_clip(16, name="oracle")
    protocol = StandardProtocol(None)
    oracle = ForwardOracle(protocol.prepare(sample))
    protocol.tracker = oracle
    result, _ = evaluate_video(protocol, sample, "strided", index=0)
    assert result.num_points > 12  # queries on frames 0, 5, 10, 15
    assert result.metrics["average_jaccard"] == 1.0
    assert result.metrics["occlusion_accuracy"] == 1.0
    assert oracle.calls == 2  # forward and reversed
    # without the reversed pass the frames before each query are wrong
    oracle.bidirectional = True
    result, _ = evaluate_video(protocol, sample, "strided", index=0)
    assert result.metrics["average_jaccard"] < 0.9


def test_first_mode_runs_forward_only():
    sample = make_clip(12)
    protocol = StandardProtocol(None)
    protocol.tracker = oracle = ForwardOracle(protocol.prepare(sample))
    result, _ = evaluate_video(protocol, sample, "first", index=0)
    assert oracle.calls == 1
    assert result.metrics["average_jaccard"] == 1.0


def test_reversed_pass_is_skipped_when_every_query_is_on_frame_zero():
    clip = StandardProtocol(None).prepare(make_clip(8, occluder=False))
    oracle = ForwardOracle(clip)
    queries = np.concatenate([np.zeros((12, 1)), clip.tracks[0]], axis=1)
    tracks, _ = track_both_ways(oracle.track, clip.video, queries)
    assert oracle.calls == 1
    np.testing.assert_array_equal(tracks, clip.tracks)


def test_tracker_output_shapes_are_checked():
    class Broken:
        bidirectional = True

        def track(self, video, queries):
            return np.zeros((len(video), len(queries) + 1, 2)), np.zeros((len(video), 1), bool)

    with pytest.raises(ValueError, match="tracker returned"):
        run_tracker(Broken(), np.zeros((4, 8, 8, 3), np.uint8), np.zeros((2, 3)), "first")
