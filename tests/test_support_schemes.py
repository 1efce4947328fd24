"""The support schemes' registry: one rule per scheme, read by every tracker.

A new scheme is registered here, in this file alone, and runs through the predictor, its
stream (points added mid-stream bring theirs, removed ones take them along), the exported
loop and its stream, which agree. The official schemes' counts, parents and fallback are
checked against what the trackers and the evaluation protocol use.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from taptr.api.online import OnlineTracker
from taptr.api.predictor import Predictor
from taptr.eval.official_protocol import grid_draws, support_points_256
from taptr.onnx.stream_tracker import OnnxOnlineTracker
from taptr.onnx.video_tracker import OnnxTracker, support_pattern
from taptr.task.support_schemes import (
    SCHEMES,
    SupportPattern,
    SupportPoints,
    SupportScheme,
    choose_scheme,
    model_points,
    register_scheme,
    support_scheme,
)
from tests.export_v3_cases import EagerGraphs, randomised_v3
from tests.test_export_v3_loop import _stream_run

RING = np.array([[np.cos(a), np.sin(a)] for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)])
"""Eight offsets on a circle of radius 1, scaled to 12 pixels of a 256 × 256 frame."""


def _ring(starts: np.ndarray, xy: np.ndarray, pattern: SupportPattern) -> SupportPoints:
    offsets = (RING * 12 / 255).astype(xy.dtype)  # (8, 2)
    positions = (xy[:, None] + offsets).reshape(-1, 2)  # (N·8, 2)
    parents = np.repeat(np.arange(len(starts)), len(offsets))
    return SupportPoints(np.repeat(np.asarray(starts, np.int64), 8), positions, parents)


@pytest.fixture
def ring():
    scheme = register_scheme(
        SupportScheme("ring", count=lambda n, pattern: 8 * n, points=_ring, added=_ring)
    )
    yield scheme
    del SCHEMES["ring"]


@pytest.fixture(scope="module")
def model():
    return randomised_v3()


def _predictor(model, **options) -> Predictor:
    return Predictor(model, device="cpu", capture="off", frames_per_call=1, **options)


def test_a_registered_scheme_runs_through_every_tracker(model, ring):
    video = np.random.default_rng(1).integers(0, 256, (10, 48, 64, 3), np.uint8)
    queries = np.array([[0, 10.0, 20.0], [4, 40.5, 33.0]], np.float32)
    predictor = _predictor(model, support_points="ring")
    assert predictor.model_points(2) == 2 + 16
    expected = predictor.track(video, queries, backward=True)
    got = OnnxTracker(graphs=EagerGraphs(model), support_points="ring").track(
        video, queries, backward=True
    )
    np.testing.assert_allclose(got.tracks, expected.tracks[0].numpy(), atol=2e-3, rtol=0)
    np.testing.assert_allclose(
        got.visibility_logits, expected.visibility_logits[0].numpy(), atol=1e-3, rtol=0
    )
    without = _predictor(model, support_points="none").track(video, queries, backward=True)
    assert not torch.allclose(without.tracks, expected.tracks, atol=1e-4)  # the ring counts


def test_a_registered_scheme_follows_points_added_and_removed(model, ring):
    frames = np.random.default_rng(2).integers(0, 256, (12, 48, 64, 3), np.uint8)
    plan = {
        0: [("add", np.array([[0, 10.0, 12.0], [0, 50.0, 30.0]], np.float32))],
        3: [("add", np.array([[4, 30.0, 20.0]], np.float32))],  # brings its ring
        7: [("remove", [0])],  # takes its ring along
    }
    online = OnlineTracker(_predictor(model, support_points="ring"))
    state = online.start(frame_size=(48, 64))
    expected = _stream_run(online, lambda: state, frames, plan)
    assert state.support == "ring" and int(state.is_context.sum()) == 2 * 8
    onnx = OnnxOnlineTracker(OnnxTracker(graphs=EagerGraphs(model), support_points="ring"))
    stream = onnx.start(frame_size=(48, 64))
    got = _stream_run(onnx, lambda: stream, frames, plan)
    assert len(stream.loop.start_frames) == 2 + 2 * 8
    assert got[0].keys() == expected[0].keys()
    for key, value in expected[0].items():
        np.testing.assert_allclose(got[0][key], value, atol=2e-3, rtol=0)


def test_counts_parents_and_the_fallback_are_the_registry_s():
    pattern = SupportPattern.normalised()
    local = support_scheme("local_and_grid")
    assert choose_scheme("local_and_grid", 32, pattern).name == "local_and_grid"
    assert choose_scheme("local_and_grid", 33, pattern).name == "grid"  # past the budget
    assert choose_scheme("local_and_grid", 1000, pattern, asked="local_and_grid") is local
    counts = {name: model_points(SCHEMES[name], 3, pattern) for name in SCHEMES}
    assert counts == {"random": 3, "local_and_grid": 3 + 3 * 63 + 36, "grid": 39, "none": 3}
    padded = SupportPattern.normalised(context_points=800)
    assert model_points(SCHEMES["random"], 3, padded) == 800
    xy = np.array([[0.5, 0.5], [0.1, 0.9]], np.float32)
    points = local.points(np.array([4, 2]), xy, pattern)
    assert points.positions.dtype == np.float32 and len(points.parents) == 2 * 63 + 36
    assert (points.parents[:63] == 0).all() and (points.parents[63:126] == 1).all()
    assert (points.parents[126:] == -1).all() and (points.start_frames[:63] == 4).all()
    assert len(local.added(np.array([7]), xy[:1], pattern).parents) == 63
    assert len(support_scheme("grid").added(np.array([7]), xy[:1], pattern).parents) == 0
    with pytest.raises(ValueError, match="support_points must be one of random"):
        support_scheme("rings")
    with pytest.raises(ValueError, match="random context points"):
        SCHEMES["random"].points(np.array([0]), xy[:1], padded)


def test_every_caller_gets_the_same_points(model):
    # the evaluation's 256-pixel points, the predictor's and the export's normalised ones
    queries = np.array([[0, 30.0, 40.0], [5, 128.0, 200.0]])
    points, kind = support_points_256(queries, grid_draws(0)[0])
    assert (kind == np.repeat([0, 1, 2], [2, 126, 36])).all()
    normalised = SupportPattern.normalised(np.float64)
    expected = support_scheme("local_and_grid").points(
        np.array([0, 5]), queries[:, 1:] / 255, normalised
    )
    np.testing.assert_allclose(points[2:, 1:] / 255, expected.positions, atol=1e-12)
    exported = support_pattern(EagerGraphs(model).manifest)
    float32 = SupportPattern.normalised(np.float32)
    np.testing.assert_array_equal(exported.local_offsets, float32.local_offsets)
    np.testing.assert_array_equal(exported.grid_start_frames, float32.grid_start_frames)
