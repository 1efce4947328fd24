"""Frame-by-frame tracking of a video equals tracking it in memory, and holds few frames."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import taptr
from taptr.api.streaming import draw_final, track_frames, track_frames_both_ways
from taptr.viz.draw import draw_tracks, point_colors

QUERIES = np.array([[0, 10, 20], [3, 55, 39], [6, 5, 5]], np.float32)


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return taptr.build_model("tiny")


def _video(frames: int) -> np.ndarray:
    return (np.random.default_rng(1).random((frames, 40, 56, 3)) * 255).astype(np.uint8)


@pytest.mark.parametrize(("frames", "context", "chunk"), [(21, 0, 4), (13, 10, 3), (50, 0, 8)])
def test_streamed_tracks_and_overlay_equal_the_in_memory_ones(model, frames, context, chunk):
    predictor = taptr.Predictor(model, device="cpu", dtype=torch.float64, context_points=context)
    video = _video(frames)
    expected = predictor.track(video, QUERIES)
    batches = list(track_frames(predictor, iter(video), QUERIES, num_frames=frames, chunk=chunk))
    assert [b.first_frame for b in batches] == sorted({b.first_frame for b in batches})
    tracks = np.concatenate([b.tracks for b in batches])
    visibility = np.concatenate([b.visibility for b in batches])
    np.testing.assert_array_equal(np.concatenate([b.frames for b in batches]), video)
    np.testing.assert_allclose(tracks, expected.tracks[0].numpy(), atol=1e-6, rtol=0)
    np.testing.assert_array_equal(visibility, expected.visibility[0].numpy())
    overlay = np.stack(list(draw_final(iter(batches), QUERIES)))
    reference = draw_tracks(video, tracks, visibility, query_frames=QUERIES[:, 0].astype(int))
    np.testing.assert_array_equal(overlay, reference)
    model.float()


@pytest.mark.parametrize(("frames", "context", "chunk"), [(21, 0, 4), (13, 10, 3)])
def test_streamed_both_ways_equals_the_in_memory_backward_tracking(model, frames, context, chunk):
    predictor = taptr.Predictor(model, device="cpu", dtype=torch.float64, context_points=context)
    video = _video(frames)
    expected = predictor.track(video, QUERIES, backward=True)
    reversed_counts = []
    batches = list(
        track_frames_both_ways(
            predictor,
            lambda: iter(video),
            lambda: iter(video[::-1]),
            QUERIES,
            num_frames=frames,
            chunk=chunk,
            on_reversed=reversed_counts.append,
        )
    )
    assert sum(reversed_counts) == frames
    tracks = np.concatenate([b.tracks for b in batches])
    visibility = np.concatenate([b.visibility for b in batches])
    logits = np.concatenate([b.visibility_logits for b in batches])
    np.testing.assert_array_equal(np.concatenate([b.frames for b in batches]), video)
    np.testing.assert_allclose(tracks, expected.tracks[0].numpy(), atol=1e-6, rtol=0)
    np.testing.assert_array_equal(visibility, expected.visibility[0].numpy())
    np.testing.assert_allclose(logits, expected.visibility_logits[0].numpy(), atol=1e-6, rtol=0)
    assert np.isfinite(logits[:3, 1]).all()  # tracked before its query frame, not hidden
    overlay = np.stack(list(draw_final(iter(batches), QUERIES, from_query_frames=False)))
    colors = point_colors(QUERIES[:, 1:])
    np.testing.assert_array_equal(overlay, draw_tracks(video, tracks, visibility, colors=colors))


def test_only_a_window_of_frames_is_held(model):
    predictor = taptr.Predictor(model, device="cpu")
    read = []

    def frames():
        for index, frame in enumerate(_video(40)):
            read.append(index)
            yield frame

    lags = []
    for batch in track_frames(predictor, frames(), QUERIES, num_frames=40, chunk=4):
        lags.append(read[-1] - (batch.first_frame + len(batch.frames) - 1))
    assert max(lags) <= 12  # never more than about a window and a chunk behind the reader


def test_errors_are_one_line(model):
    predictor = taptr.Predictor(model, device="cpu")
    with pytest.raises(ValueError, match="no frames"):
        list(track_frames(predictor, iter([]), QUERIES))
    with pytest.raises(ValueError, match="declared"):
        list(track_frames(predictor, iter(_video(9)), QUERIES, num_frames=12))
    with pytest.raises(ValueError, match="chunk"):
        list(track_frames(predictor, iter(_video(9)), QUERIES, chunk=0))
