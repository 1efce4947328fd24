"""TAPTRv3 reproduces the official streaming evaluation's outputs on generated weights.

The fixtures (tests/fixtures/v3_*.npz, compacted from ../shared/reference/golden-v3/ by
scripts/compact_golden.py) hold the official code's outputs for the ResNet-18 config on the
seed-240716 weights: a non-square 12-frame clip, a 40-frame clip, and the same 40 frames
with a 16-frame history limit.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

import taptr
from taptr.model.trajectory import QuerySet
from taptr.model.v3 import per_frame
from taptr.runtime.frames import EncodedFrames
from tests.helpers import golden_inputs, load_golden

CASES = {"v3_r18_small": None, "v3_r18_long": None, "v3_r18_fifo": 16}
"""Each case and its history limit."""


@pytest.fixture(scope="module")
def official_v3(official_v3_checkpoint):
    return taptr.load_checkpoint(official_v3_checkpoint)


def _point_major(x: torch.Tensor) -> np.ndarray:
    return x.transpose(0, 1).double().numpy()  # (T, N, ...) → (N, T, ...)


def _logit(threshold: float) -> float:
    return float(np.log(threshold / (1 - threshold)))


@pytest.mark.parametrize("execution", ["fast", "reference"])
@pytest.mark.parametrize("case", list(CASES))
def test_outputs_match_official_float32(official_v3, case, execution):
    golden = load_golden(case)
    model = copy.deepcopy(official_v3).set_execution(execution)
    video, starts, xy, labels = golden_inputs(golden)
    out = taptr.official_forward(model, video, starts, xy, labels, history_frames=CASES[case])
    positions, logits = _point_major(out["positions"]), _point_major(out["visibility_logits"])
    assert np.abs(positions - golden["out_pred_xy_norm"]).max() <= 3e-5
    assert np.abs(logits - golden["out_vis_logits"]).max() <= 5e-5

    written = np.arange(positions.shape[1])[None] > golden["in_query_t"][:, None]
    official = golden["out_vis_logits"][..., 1]
    for threshold, key in ((0.45, "out_visible"), (0.5, "out_visible_p05")):
        firm = written & (np.abs(official - _logit(threshold)) >= 1e-4)
        assert firm.sum() > 0
        visible = 1 / (1 + np.exp(-logits[..., 1])) > threshold
        assert (visible == golden[key])[firm].all()
    # frames up to the start are never written: the start state exactly
    assert np.array_equal(logits[~written], golden["out_vis_logits"][~written])
    assert np.abs(positions[~written] - golden["out_pred_xy_norm"][~written]).max() <= 1e-7

    for index, layer in enumerate(out["layers"]):
        for ours, theirs, bound in (
            (layer["positions"], golden["layers_pred_xy"][index], 3e-5),
            (layer["updated_positions"], golden["layers_ca_xy"][index], 3e-5),
            (layer["visibility_logits"], golden["layers_vis_logits"][index], 1e-4),
        ):
            assert np.abs(_point_major(ours) - theirs).max() <= bound


@pytest.mark.parametrize(("case", "bound"), [("v3_r18_small", 1e-6), ("v3_r18_long", 5e-6)])
def test_outputs_match_official_float64(official_v3, case, bound):
    golden = load_golden(case)
    double = copy.deepcopy(official_v3).double().set_execution("reference")
    out = taptr.official_forward(double, *golden_inputs(golden, torch.float64))
    # the official float64 run keeps its visibility logits in float32
    assert np.abs(_point_major(out["positions"]) - golden["f64_out_pred_xy_norm"]).max() <= bound
    assert (
        np.abs(_point_major(out["visibility_logits"]) - golden["f64_out_vis_logits"]).max() <= 1e-5
    )


def test_point_contexts_and_memory_match(official_v3):
    golden = load_golden("v3_r18_small")
    video, starts, xy, _ = golden_inputs(golden)
    with torch.no_grad():
        features = official_v3.encode(video)
        assert [list(s) for s in features.spatial_shapes] == golden["dbg_spatial_shapes"].tolist()
        frames, tokens = golden["dbg_memory_frames"], golden["dbg_memory_token_idx"]
        memory = features.memory[0][frames][:, tokens, :32].numpy()
        assert np.abs(memory - golden["dbg_memory_sample"]).max() <= 1e-4
        contexts = torch.stack(
            [
                official_v3.point_queries(
                    features.memory[:, t], features.spatial_shapes, xy[i : i + 1][None]
                )[1][0, 0]
                for i, t in enumerate(starts.tolist())
            ]
        )  # (N, K, K, C)
    assert np.abs(contexts.numpy() - golden["init_context_feature"]).max() <= 1e-4
    assert np.abs(contexts[:, 1, 1].numpy() - golden["init_query_feature"]).max() <= 1e-4


def test_history_limit_holds_the_last_frames(official_v3):
    """After 40 frames with a 16-frame limit, the held content is frames 24..39."""
    golden = load_golden("v3_r18_fifo")
    video, starts, xy, labels = golden_inputs(golden)
    model = copy.deepcopy(official_v3).eval()
    queries = QuerySet(starts[None], xy[None], (labels == 1)[None])
    state = per_frame.start_state(model, queries, torch.float32, history_frames=16)
    frames = EncodedFrames(model, video)
    with torch.no_grad():
        for _ in range(video.shape[1]):
            per_frame.decode_frame(model, state, frames)
    assert state.history.length == 16 and state.history.first == 24
    held = state.history.content[0].numpy()  # (N, 16, C)
    official = golden["dbg_content_final"]  # (N, 16, C): frames 25..39, then a free slot
    assert np.abs(held[:, 1:] - official[:, :15]).max() <= 1e-4
