"""Online tracking equals offline tracking, adds and removes points, holds bounded memory."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from taptr.api.online import OnlineTracker
from tests.helpers import float64_tiny_predictor, noise_video


@pytest.fixture(scope="module")
def predictor():
    return float64_tiny_predictor()


def _stream(online, state, video, chunk=1):
    updates = [online.step(state, video[i : i + chunk]) for i in range(0, len(video), chunk)]
    updates.append(online.finish(state))
    return updates


def _concat(updates):
    frames = [u for u in updates if u.tracks.shape[0]]
    assert [u.first_frame for u in frames] == sorted(u.first_frame for u in frames)
    return torch.cat([u.tracks for u in frames]), torch.cat([u.visibility for u in frames])


QUERIES = np.array([[0, 10, 20], [3, 55, 39], [6, 5, 5]], np.float32)


@pytest.mark.parametrize(
    ("frames", "declare", "chunk"), [(20, False, 1), (9, False, 3), (5, False, 2), (50, True, 1)]
)
def test_stream_equals_offline(predictor, frames, declare, chunk):
    video = noise_video(frames)
    queries = QUERIES.copy()
    queries[:, 0] = np.minimum(queries[:, 0], frames - 1)
    offline = predictor.track(video, queries)
    online = OnlineTracker(predictor)
    state = online.start(num_frames=frames if declare else None, frame_size=(40, 56))
    online.add_queries(state, queries)
    tracks, visibility = _concat(_stream(online, state, video, chunk))
    assert tracks.shape == (frames, 3, 2)
    torch.testing.assert_close(tracks, offline.tracks[0], atol=1e-6, rtol=0)
    assert torch.equal(visibility, offline.visibility[0])


def test_point_added_on_the_newest_frame_equals_offline(predictor):
    video = noise_video(24, seed=1)
    offline = predictor.track(video, QUERIES)
    online = OnlineTracker(predictor)
    state = online.start(frame_size=(40, 56))
    online.add_queries(state, QUERIES[:1])
    updates = []
    for frame in range(24):
        updates.append(online.step(state, video[frame]))
        for t, x, y in QUERIES[1:]:
            if frame == t:
                online.add_queries(state, [[t, x, y]])
    updates.append(online.finish(state))
    tracks, _ = _concat(updates)
    torch.testing.assert_close(tracks, offline.tracks[0], atol=1e-6, rtol=0)


def test_memory_is_bounded_by_the_window(predictor):
    online = OnlineTracker(predictor)
    state = online.start(frame_size=(40, 56))
    online.add_queries(state, [[0, 10, 10]])
    video = noise_video(60, seed=2)
    held, delays = [], []
    for frame in range(60):
        update = online.step(state, video[frame])
        held.append(len(state.encoded))
        delays.append(state.num_seen - state.emitted)
        assert update.tracks.shape[1] == 1
    assert max(held) <= 13
    assert max(delays[12:]) <= 12
    assert state.tracker.content.end - state.tracker.content.first <= 12


def test_remove_points(predictor):
    video = noise_video(16, seed=3)
    online = OnlineTracker(predictor)
    state = online.start(frame_size=(40, 56))
    ids = online.add_queries(state, QUERIES)
    for frame in range(10):
        online.step(state, video[frame])
    online.remove_queries(state, [ids[1]])
    for frame in range(10, 16):
        update = online.step(state, video[frame])
    final = online.finish(state)
    assert final.point_ids == [ids[0], ids[2]] and final.tracks.shape[1] == 2
    with pytest.raises(ValueError, match="unknown point ids"):
        online.remove_queries(state, [99])
    del update


def test_errors(predictor):
    online = OnlineTracker(predictor)
    state = online.start()
    with pytest.raises(ValueError, match="frame size is unknown"):
        online.add_queries(state, QUERIES)
    video = noise_video(12)
    for frame in range(12):
        online.step(state, video[frame])
    with pytest.raises(ValueError, match="after frame"):
        online.add_queries(state, [[0, 1, 1]])
    with pytest.raises(ValueError, match="outside the 56x40 frame"):
        online.add_queries(state, [[11, 60, 1]])
    with pytest.raises(ValueError, match="frame size changed"):
        online.step(state, np.zeros((32, 32, 3), np.uint8))
    declared = online.start(num_frames=3)
    online.step(declared, video[:3])
    with pytest.raises(ValueError, match="more frames than the declared"):
        online.step(declared, video[3])
    short = online.start(num_frames=5)
    online.step(short, video[:2])
    with pytest.raises(ValueError, match="ended after 2 of 5"):
        online.finish(short)


def test_stream_queries_go_through_the_predictor_validator(predictor, monkeypatch):
    online = OnlineTracker(predictor)
    state = online.start(frame_size=(40, 56))
    with pytest.raises(ValueError, match="real numbers"):
        online.add_queries(state, [["a", "b", "c"]])
    monkeypatch.setenv("TAPTR_MAX_POINTS", "2")
    with pytest.raises(ValueError, match="TAPTR_MAX_POINTS"):
        online.add_queries(state, QUERIES)
    assert online.add_queries(state, QUERIES[:2]) == [0, 1]  # no length: any future frame
