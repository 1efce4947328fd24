"""The predictor: inputs, pixel mapping, query frames, grids, backward tracking, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import taptr
from taptr.api.inputs import grid_queries


@pytest.fixture(scope="module")
def predictor():
    torch.manual_seed(0)
    return taptr.Predictor(taptr.build_model("tiny"), device="cpu")


@pytest.fixture(scope="module")
def video():
    rng = np.random.default_rng(0)
    return (rng.random((14, 40, 72, 3)) * 255).astype(np.uint8)


QUERIES = np.array([[0, 10.0, 20.0], [5, 71.0, 39.0], [13, 0.0, 0.0], [7, 35.5, 12.25]], np.float32)


def test_shapes_and_queries_returned_exactly(predictor, video):
    result = predictor.track(video, QUERIES)
    assert result.tracks.shape == (1, 14, 4, 2) and result.visibility.shape == (1, 14, 4)
    assert result.visibility_logits.shape == (1, 14, 4) and result.queries.shape == (1, 4, 3)
    for n, (t, x, y) in enumerate(QUERIES):
        assert result.tracks[0, int(t), n].tolist() == [x, y]
        assert bool(result.visibility[0, int(t), n])
        assert not result.visibility[0, : int(t), n].any()  # not tracked before the query frame


def test_numpy_and_torch_inputs_agree(predictor, video):
    from_numpy = predictor.track(video, QUERIES)
    as_uint8 = torch.from_numpy(video).permute(0, 3, 1, 2)[None]
    from_uint8 = predictor.track(as_uint8, torch.from_numpy(QUERIES))
    from_float = predictor.track(as_uint8.float() / 255, QUERIES[None])
    torch.testing.assert_close(from_uint8.tracks, from_numpy.tracks)
    torch.testing.assert_close(from_float.tracks, from_numpy.tracks)


def test_positions_map_back_per_axis(video):
    """The model sees normalised positions; the mapping back must undo the mapping in."""
    torch.manual_seed(0)
    model = taptr.build_model("tiny")
    results = []
    for size in [(40, 72), (64, 64), (32, 96)]:
        predictor = taptr.Predictor(model, input_size=size, device="cpu")
        results.append(predictor.track(video, QUERIES))
    # same relative positions in any model resolution for the (untouched) query frames
    for result in results:
        assert result.tracks[0, 0, 0].tolist() == [10.0, 20.0]
    # model input = video size: tracks are pixels of the video, inside the frame
    inside = results[0].tracks[0]
    assert float(inside[..., 0].min()) >= 0 and float(inside[..., 0].max()) <= 71
    assert float(inside[..., 1].min()) >= 0 and float(inside[..., 1].max()) <= 39


def test_batch_is_processed_one_video_at_a_time(predictor, video):
    batch = torch.from_numpy(np.stack([video, video[::-1].copy()])).permute(0, 1, 4, 2, 3)
    both = predictor.track(batch, QUERIES)
    second = predictor.track(video[::-1].copy(), QUERIES)
    torch.testing.assert_close(both.tracks[1], second.tracks[0])


def test_grid_queries(predictor, video):
    result = predictor.track(video, grid_size=3, grid_query_frame=2)
    assert result.tracks.shape == (1, 14, 9, 2)
    queries = grid_queries(3, 2, 40, 72)
    torch.testing.assert_close(result.queries[0], queries)
    assert queries[:, 1].min() > 0 and queries[:, 1].max() < 71
    assert (queries[:, 0] == 2).all()


def test_backward_fills_frames_before_the_query(predictor, video):
    forward = predictor.track(video, QUERIES)
    both = predictor.track(video, QUERIES, backward=True)
    torch.testing.assert_close(both.tracks[0, 5:, 1], forward.tracks[0, 5:, 1])
    reversed_video = video[::-1].copy()
    flipped = QUERIES.copy()
    flipped[:, 0] = 13 - flipped[:, 0]
    backward = predictor.track(reversed_video, flipped)
    torch.testing.assert_close(both.tracks[0, :5, 1], backward.tracks[0].flip(0)[:5, 1])
    assert torch.isfinite(both.visibility_logits[0, :5, 1]).all()


@pytest.mark.parametrize(
    ("video_input", "queries", "message"),
    [
        (np.zeros((4, 8, 8, 3), np.float32), QUERIES[:1], "uint8"),
        (np.zeros((4, 8, 8)), QUERIES[:1], r"\(T, H, W, 3\)"),
        (torch.full((1, 4, 3, 8, 8), 2.0), QUERIES[:1], "divide by 255"),
        (np.zeros((4, 8, 8, 3), np.uint8), np.array([[4, 1, 1]]), r"outside \[0, 4\)"),
        (np.zeros((4, 8, 8, 3), np.uint8), np.array([[0, 8, 1]]), "outside the 8x8 frame"),
        (np.zeros((4, 8, 8, 3), np.uint8), np.array([[0, np.nan, 1]]), "NaN"),
        (np.zeros((4, 8, 8, 3), np.uint8), np.array([[0.5, 1, 1]]), "whole frame"),
        (np.zeros((4, 8, 8, 3), np.uint8), np.array([0, 1, 1, 2]), r"\(N, 3\)"),
        (np.zeros((0, 8, 8, 3), np.uint8), QUERIES[:1], "no frames"),
    ],
)
def test_bad_inputs_are_named(predictor, video_input, queries, message):
    with pytest.raises(ValueError, match=message):
        predictor.track(video_input, queries)


def test_exactly_one_of_queries_or_grid(predictor, video):
    with pytest.raises(ValueError, match="exactly one"):
        predictor.track(video)
    with pytest.raises(ValueError, match="exactly one"):
        predictor.track(video, QUERIES, grid_size=2)


def test_from_pretrained_preset_and_missing_name(caplog):
    predictor = taptr.Predictor.from_pretrained("tiny", device="cpu")
    assert "UNTRAINED" in caplog.text
    assert predictor.input_size == (64, 64)
    with pytest.raises(FileNotFoundError, match="known names"):
        taptr.Predictor.from_pretrained("no-such-model")


def test_from_pretrained_checkpoint_path(tmp_path):
    from taptr.weights.checkpoint import save_checkpoint

    model = taptr.build_model("tiny")
    path = save_checkpoint(model, tmp_path / "tiny.pth")
    predictor = taptr.Predictor.from_pretrained(path, device="cpu")
    assert predictor.model.config == model.config
