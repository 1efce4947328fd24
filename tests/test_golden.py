"""The model reproduces the official code's outputs on the seed-1 generated weights."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

import taptr
from tests.helpers import golden_inputs, load_golden

CASES = ["v2_small_nonsquare", "v2_long"]


@pytest.fixture(scope="module")
def official_model(official_checkpoint):
    return taptr.load_checkpoint(official_checkpoint)


def _point_major(x: torch.Tensor) -> np.ndarray:
    return x.transpose(0, 1).double().numpy()  # (T, N, ...) → (N, T, ...)


@pytest.mark.parametrize("execution", ["fast", "reference"])
@pytest.mark.parametrize("case", CASES)
def test_outputs_match_official_float32(official_model, case, execution):
    golden = load_golden(case)
    model = copy.deepcopy(official_model).set_execution(execution)
    out = taptr.official_forward(model, *golden_inputs(golden))
    positions, logits = _point_major(out["positions"]), _point_major(out["visibility_logits"])
    assert np.abs(positions - golden["out_pred_xy_norm"]).max() <= 3e-5
    assert np.abs(logits - golden["out_vis_logits"]).max() <= 3e-5

    num_frames = positions.shape[1]
    written = np.arange(num_frames)[None] > golden["in_query_t"][:, None]
    firm = written & (np.abs(golden["out_vis_logits"][..., 1]) >= 1e-4)
    assert ((logits[..., 1] > 0) == golden["out_visible"])[firm].all()
    # frames up to the start are never written: the one-hot and the clamped query
    assert np.array_equal(logits[~written], golden["out_vis_logits"][~written])
    assert np.abs(positions[~written] - golden["out_pred_xy_norm"][~written]).max() <= 1e-7

    for index, layer in enumerate(out["layers"]):
        assert (
            np.abs(_point_major(layer["positions"]) - golden["layers_pred_xy"][index]).max() <= 3e-5
        )
        assert (
            np.abs(
                _point_major(layer["visibility_logits"]) - golden["layers_vis_logits"][index]
            ).max()
            <= 3e-5
        )
        assert (
            np.abs(_point_major(layer["updated_positions"]) - golden["layers_ca_xy"][index]).max()
            <= 3e-5
        )


@pytest.mark.parametrize("case", CASES)
def test_outputs_match_official_float64(official_model, case):
    golden = load_golden(case)
    double = copy.deepcopy(official_model).double()
    out = taptr.official_forward(double, *golden_inputs(golden, torch.float64))
    # everything in float64 against the official float64 run: within 1e-6 (README of the fixtures)
    assert np.abs(_point_major(out["positions"]) - golden["f64_out_pred_xy_norm"]).max() <= 1e-6
    assert (
        np.abs(_point_major(out["visibility_logits"]) - golden["f64_out_vis_logits"]).max() <= 1e-6
    )


def test_intermediate_features_match(official_model):
    golden = load_golden("v2_small_nonsquare")
    video, starts, xy, _ = golden_inputs(golden)
    with torch.no_grad():
        frame0 = video[0, :1]
        maps = official_model.backbone(frame0)
        projected = official_model.input_projections(maps)
        for level in range(4):
            assert list(maps[level].shape[1:]) == golden[f"dbg_backbone_l{level}_shape"].tolist()
            idx = golden[f"dbg_backbone_l{level}_f0_idx"]
            assert (
                np.abs(
                    maps[level][0].flatten()[idx].numpy()
                    - golden[f"dbg_backbone_l{level}_f0_sample"]
                ).max()
                <= 1e-4
            )
            idx = golden[f"dbg_input_proj_l{level}_f0_idx"]
            sample = golden[f"dbg_input_proj_l{level}_f0_sample"]
            assert np.abs(projected[level][0].flatten()[idx].numpy() - sample).max() <= 1e-4
        features = official_model.encode(video)
        assert [list(s) for s in features.spatial_shapes] == golden["dbg_spatial_shapes"].tolist()
        frames, tokens = golden["dbg_memory_frames"], golden["dbg_memory_token_idx"]
        memory = features.memory[0][frames][:, tokens, :32].numpy()
        assert np.abs(memory - golden["dbg_memory_sample"]).max() <= 1e-4
        assert (
            np.abs(features.memory[0].mean((1, 2)).numpy() - golden["dbg_memory_frame_mean"]).max()
            <= 1e-5
        )

        content = torch.stack(
            [
                official_model.initial_content(
                    features.memory[:, t], features.spatial_shapes, xy[i : i + 1][None]
                )[0, 0]
                for i, t in enumerate(starts.tolist())
            ]
        )
        assert np.abs(content.numpy() - golden["init_query_feature"]).max() <= 1e-4
