"""The TAP-Vid metric: hand-checked fixture cases, tapnet semantics, and the adapter."""

from __future__ import annotations

import json

import numpy as np
import pytest

from taptr.eval.metrics import (
    METRIC_NAMES,
    compute_tapvid_metrics,
    evaluation_mask,
    mean_over_videos,
    tapvid_metrics,
)
from tests.helpers import FIXTURES

CASES = json.loads((FIXTURES / "tapvid-metric-cases.json").read_text())["cases"]


def _tapnet_inputs(case: dict) -> dict:
    """A fixture case as batched tapnet arrays (B = 1)."""
    return {
        "query_points": np.array(case["query_points_tyx"])[None],
        "gt_occluded": np.array(case["gt_occluded"])[None],
        "gt_tracks": np.array(case["gt_tracks_xy"])[None],
        "pred_occluded": np.array(case["pred_occluded"])[None],
        "pred_tracks": np.array(case["pred_tracks_xy"])[None],
        "query_mode": case["query_mode"],
    }


@pytest.mark.parametrize("case", CASES, ids=[c["name"] for c in CASES])
def test_fixture_cases(case):
    result = compute_tapvid_metrics(**_tapnet_inputs(case))
    assert set(result) == set(METRIC_NAMES)
    for name, expected in case["expected"].items():
        assert result[name].shape == (1,)
        assert result[name][0] == pytest.approx(expected, abs=1e-9), name


@pytest.mark.parametrize("case", CASES, ids=[c["name"] for c in CASES])
def test_adapter_converts_our_conventions(case):
    """(t, x, y) queries, (T, N) visibility and pixel centres at integers give the same numbers."""
    tyx = np.array(case["query_points_tyx"])
    # our pixels are tapnet's raster pixels − 0.5
    queries = np.stack([tyx[:, 0], tyx[:, 2] - 0.5, tyx[:, 1] - 0.5], axis=-1)
    result = tapvid_metrics(
        queries,
        np.array(case["gt_tracks_xy"]).transpose(1, 0, 2) - 0.5,
        ~np.array(case["gt_occluded"]).T,
        np.array(case["pred_tracks_xy"]).transpose(1, 0, 2) - 0.5,
        ~np.array(case["pred_occluded"]).T,
        case["query_mode"],
    )
    for name, expected in case["expected"].items():
        assert result[name] == pytest.approx(expected, abs=1e-9), name


def test_trackwise_metrics_of_two_tracks():
    first = _tapnet_inputs(CASES[0])
    occluded = _tapnet_inputs(CASES[2])
    assert CASES[2]["query_mode"] == "first"
    merged = {
        key: np.concatenate([first[key], occluded[key]], axis=1)
        for key in ("query_points", "gt_occluded", "gt_tracks", "pred_occluded", "pred_tracks")
    }
    result = compute_tapvid_metrics(**merged, query_mode="first", get_trackwise_metrics=True)
    assert result["average_jaccard"].shape == (1, 2)
    np.testing.assert_allclose(result["average_jaccard"], [[0.36666667, 0.13333333]], atol=1e-6)
    # per video, both tracks pool their frames into one value
    video = compute_tapvid_metrics(**merged, query_mode="first")
    assert video["average_jaccard"].shape == (1,)


def test_batch_of_videos_matches_videos_one_by_one():
    rng = np.random.default_rng(0)
    batch, points, frames = 3, 5, 9
    inputs = {
        "query_points": np.stack(
            [rng.integers(0, frames, (batch, points)), *rng.uniform(0, 256, (2, batch, points))],
            axis=-1,
        ),
        "gt_occluded": rng.random((batch, points, frames)) < 0.3,
        "gt_tracks": rng.uniform(0, 256, (batch, points, frames, 2)),
        "pred_occluded": rng.random((batch, points, frames)) < 0.3,
    }
    inputs["pred_tracks"] = inputs["gt_tracks"] + rng.normal(0, 6, inputs["gt_tracks"].shape)
    for mode in ("first", "strided"):
        together = compute_tapvid_metrics(**inputs, query_mode=mode)
        for b in range(batch):
            alone = compute_tapvid_metrics(
                **{k: v[b : b + 1] for k, v in inputs.items()}, query_mode=mode
            )
            for name in METRIC_NAMES:
                assert together[name].shape == (batch,)
                assert together[name][b] == pytest.approx(alone[name][0], nan_ok=True)


def test_first_mode_ignores_frames_up_to_the_query_and_strided_does_not():
    inputs = _tapnet_inputs(CASES[0])  # query frame 1, ground truth occluded on frame 0
    changed = dict(inputs, pred_occluded=inputs["pred_occluded"].copy())
    changed["pred_occluded"][0, 0, :2] = True  # frame 0 and the query frame
    for name in METRIC_NAMES:
        assert compute_tapvid_metrics(**changed)[name] == pytest.approx(
            compute_tapvid_metrics(**inputs)[name]
        )
    strided = compute_tapvid_metrics(**dict(inputs, query_mode="strided"))
    strided_changed = compute_tapvid_metrics(**dict(changed, query_mode="strided"))
    # frame 0 is now a correct occlusion and no longer a false positive
    assert strided["occlusion_accuracy"][0] == pytest.approx(2 / 4)
    assert strided_changed["occlusion_accuracy"][0] == pytest.approx(3 / 4)
    assert strided_changed["jaccard_16"][0] == pytest.approx(2 / 3)


def test_thresholds_are_strict():
    gt = np.zeros((1, 1, 3, 2))
    pred = gt.copy()
    pred[0, 0, 1:, 0] = (1.9999, 2.0)
    result = compute_tapvid_metrics(
        np.zeros((1, 1, 3)), np.zeros((1, 1, 3), bool), gt, np.zeros((1, 1, 3), bool), pred, "first"
    )
    assert result["pts_within_2"][0] == pytest.approx(0.5)
    assert result["pts_within_4"][0] == pytest.approx(1.0)


def test_query_frames_are_rounded():
    mask = evaluation_mask(np.array([[1.4, 2.6]]).round().astype(int), 5, "first")
    np.testing.assert_array_equal(mask[0, 0], [False, False, True, True, True])
    inputs = _tapnet_inputs(CASES[0])
    inputs["query_points"] = inputs["query_points"] + np.array([0.4, 0, 0])
    assert compute_tapvid_metrics(**inputs)["average_jaccard"][0] == pytest.approx(0.36666667)


def test_strided_mask_scores_every_other_frame():
    mask = evaluation_mask(np.array([[0, 2]]), 4, "strided")
    np.testing.assert_array_equal(mask[0], [[0, 1, 1, 1], [1, 1, 0, 1]])


def test_benchmark_is_the_plain_mean_over_videos():
    good = dict.fromkeys(METRIC_NAMES, 1.0)
    bad = dict.fromkeys(METRIC_NAMES, 0.0)
    unscored = dict.fromkeys(METRIC_NAMES, float("nan"))
    mean = mean_over_videos([good, bad, bad, unscored])
    assert mean["average_jaccard"] == pytest.approx(1 / 3)


def test_bad_inputs_are_named():
    inputs = _tapnet_inputs(CASES[0])
    with pytest.raises(ValueError, match="unknown query mode"):
        compute_tapvid_metrics(**dict(inputs, query_mode="last"))
    with pytest.raises(ValueError, match="tracks must both be"):
        compute_tapvid_metrics(**dict(inputs, pred_tracks=inputs["pred_tracks"][:, :, :3]))
