"""``taptr analyze attention``: hooks that only read, exact offsets, statistics, figure, CLI."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

import taptr
from taptr.api.inputs import grid_queries
from taptr.apps.attention_analysis import (
    DISTANCE_EDGES,
    analyze_attention,
    attention_statistics,
    draw_attention,
    record_cross_attention,
)
from taptr.cli.main import main as cli_main
from taptr.windows import window_ranges

FRAMES, HEIGHT, WIDTH = 11, 40, 56

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def video():
    """A textured image sliding right by 2 px per frame, (T, H, W, 3) uint8."""
    rng = np.random.default_rng(0)
    base = cv2.resize(rng.random((12, 20, 3), dtype=np.float32), (WIDTH + 40, HEIGHT))
    base = (255 * base).astype(np.uint8)
    return np.stack([base[:, 40 - 2 * t : 40 - 2 * t + WIDTH] for t in range(FRAMES)])


@pytest.fixture(scope="module")
def predictor():
    torch.manual_seed(0)
    # context points exercise the slicing to the analysed points
    return taptr.Predictor(taptr.build_model("tiny"), device="cpu", context_points=24)


def test_hooks_only_read_and_are_removed(predictor, video):
    queries = grid_queries(3, 0, HEIGHT, WIDTH)
    plain = predictor.track(video, queries)
    records = analyze_attention(predictor, video, queries)
    recorded = predictor.track(video, queries)  # after the hooks are gone
    with record_cross_attention(predictor.model, predictor.input_size, 9):
        hooked = predictor.track(video, queries)
    for result in (recorded, hooked):
        torch.testing.assert_close(result.tracks, plain.tracks, rtol=0, atol=0)
        torch.testing.assert_close(result.visibility_logits, plain.visibility_logits)
    decoder = predictor.model.decoder
    assert not decoder._forward_pre_hooks
    assert all(not layer.cross_attention._forward_hooks for layer in decoder.layers)
    assert len(records) == predictor.model.num_layers


def test_only_tracked_entries_of_the_analysed_points(predictor, video):
    query_frame = 2
    queries = grid_queries(2, query_frame, HEIGHT, WIDTH)
    records = analyze_attention(predictor, video, queries)
    model = predictor.model
    ranges = window_ranges(FRAMES, model.window_size, model.window_stride)
    tracked = sum(max(0, last - max(first, query_frame + 1) + 1) for first, last in ranges)
    config = model.config
    for record in records:
        weights, offsets = record.stacked()
        levels = weights.shape[2]
        assert weights.shape == (4 * tracked, config.num_heads, levels, weights.shape[3])
        assert offsets.shape == (*weights.shape, 2)
        np.testing.assert_allclose(weights.sum((2, 3)), 1, atol=1e-5)


def test_offsets_are_model_input_pixels(video):
    """With zero offset weights the offsets are the radial-grid bias: head 0 looks along +x,
    sample p of level l at p + 1 feature pixels, i.e. (p + 1)·(W_in − 1)/W_l input pixels."""
    torch.manual_seed(1)
    model = taptr.build_model("tiny")
    attention = model.decoder.layers[0].cross_attention
    with torch.no_grad():
        attention.sampling_offsets.weight.zero_()
    predictor = taptr.Predictor(model, device="cpu", context_points=0)
    records = analyze_attention(predictor, video, grid_queries(2, 0, HEIGHT, WIDTH))
    _, offsets = records[0].stacked()
    with torch.no_grad():
        features = model.encode_images(torch.zeros(1, 3, *predictor.input_size))
    width_in = predictor.input_size[1]
    for level, (_, level_width) in enumerate(features.spatial_shapes):
        for point in range(offsets.shape[3]):
            expected = (point + 1) * (width_in - 1) / level_width
            np.testing.assert_allclose(offsets[:, 0, level, point, 0], expected, rtol=1e-5)
            np.testing.assert_allclose(offsets[:, 0, level, point, 1], 0, atol=1e-4)


def test_statistics_and_figure(predictor, video):
    records = analyze_attention(predictor, video, grid_queries(3, 0, HEIGHT, WIDTH))
    statistics = attention_statistics(records, bins=17)
    assert statistics["histogram_bins"] == 17 and statistics["histogram_radius"] >= 1
    assert len(statistics["layers"]) == len(records)
    for layer in statistics["layers"]:
        assert len(layer["mass_by_distance"]) == len(DISTANCE_EDGES) - 1
        assert sum(layer["mass_by_distance"]) == pytest.approx(1, abs=1e-4)
        assert sum(layer["samples_by_distance"]) == pytest.approx(1, abs=1e-4)
        assert sum(layer["mass_by_level"]) == pytest.approx(1, abs=1e-4)
        histogram = np.asarray(layer["histogram"])
        assert histogram.shape == (17, 17)
        total = histogram.sum() + layer["mass_outside_histogram"]
        assert total == pytest.approx(1, abs=1e-4)
        assert 0 < layer["normalised_entropy"] <= 1 + 1e-6
        assert 0 < layer["max_weight"] <= 1
        assert layer["attention_weighted_distance"] > 0
    json.dumps(statistics)  # JSON-ready
    image = draw_attention(statistics, "tiny")
    assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
    assert image.shape[1] >= 640 and image.std() > 10
    with pytest.raises(ValueError, match="no attention"):
        attention_statistics([type(records[0])()])


def test_cli(tmp_path, video, capsys):
    folder = tmp_path / "frames"
    folder.mkdir()
    for index, frame in enumerate(video):
        cv2.imwrite(str(folder / f"{index:03d}.png"), frame[..., ::-1])
    out = tmp_path / "analysis"
    argv = ["analyze", "attention", str(folder), "--checkpoint", "tiny", "--grid", "3"]
    assert cli_main([*argv, "--device", "cpu", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "entropy" in printed and "attention.png" in printed
    report = json.loads((out / "attention.json").read_text())
    assert report["points"] == 9 and report["num_frames"] == FRAMES
    assert report["cross_attention"] == "key_aware" and len(report["layers"]) >= 1
    assert cv2.imread(str(out / "attention.png")) is not None
    bad = [*argv, "--query-frame", str(FRAMES - 1), "--out", str(out)]
    assert cli_main(bad) == 2
    assert "--query-frame" in capsys.readouterr().err


@pytest.mark.parametrize(
    "overrides",
    [{"cross_attention": "standard"}, {"position_update": False, "disentangler": False}],
)
def test_ablation_models(video, overrides):
    """The analysis reads any deformable cross-attention: standard, or without the APU."""
    import dataclasses

    torch.manual_seed(2)
    config = dataclasses.replace(taptr.get_config("tiny"), **overrides)
    predictor = taptr.Predictor(taptr.build_model(config), device="cpu")
    records = analyze_attention(predictor, video, grid_queries(2, 0, HEIGHT, WIDTH))
    statistics = attention_statistics(records)
    assert len(statistics["layers"]) == config.decoder_layers
    for layer in statistics["layers"]:
        assert sum(layer["mass_by_distance"]) == pytest.approx(1, abs=1e-4)
