"""Training losses: hand-computed cases and the official criterion fixture (loss_v2)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import taptr
from taptr.data.sampling import ClipBatch
from taptr.model.trajectory import TrackOutput
from taptr.official.convert import convert_state_dict
from taptr.train.forward import TrainingForward, batch_queries, batch_targets
from taptr.train.losses import (
    LossWeights,
    Targets,
    focal_visibility_loss,
    position_loss,
    tracking_loss,
)
from tests.helpers import load_golden


def _focal_by_hand(logit: float, target: float, alpha=0.25, gamma=2.0) -> float:
    p = 1 / (1 + math.exp(-logit))
    ce = -(target * math.log(p) + (1 - target) * math.log(1 - p))
    p_t = p if target else 1 - p
    a = alpha if target else 1 - alpha
    return a * ce * (1 - p_t) ** gamma


def test_focal_loss_matches_hand_computation():
    logits = torch.tensor(
        [[[[0.0, 2.0, -1.0]], [[1.0, -3.0, 0.5]], [[5.0, 5.0, 5.0]]]], dtype=torch.float64
    )
    visible = torch.tensor([[[True], [False], [True]]])
    mask = torch.tensor([[[True], [True], [False]]])  # the third entry does not count
    expected = sum(
        _focal_by_hand(x, t) for x, t in zip([0.0, 2.0, -1.0], [0, 1, 0], strict=True)
    ) + sum(_focal_by_hand(x, t) for x, t in zip([1.0, -3.0, 0.5], [0, 0, 1], strict=True))
    loss = focal_visibility_loss(logits, visible, mask)
    assert loss.shape == (1,)
    assert loss.item() == pytest.approx(expected / 3, rel=1e-12)  # count 2, + 1


def test_position_loss_sums_xy_and_divides_by_count_plus_one():
    predicted = torch.tensor([[[[0.5, 0.5], [0.1, 0.9]]]], dtype=torch.float64)
    target = torch.tensor([[[[0.6, 0.3], [0.1, 0.8]]]], dtype=torch.float64)
    mask = torch.tensor([[[True, True]]])
    assert position_loss(predicted, target, mask).item() == pytest.approx(0.4 / 3, rel=1e-12)
    mask = torch.tensor([[[True, False]]])
    assert position_loss(predicted, target, mask).item() == pytest.approx(0.3 / 2, rel=1e-12)


def test_taptr_v1_divides_by_the_plain_count():
    predicted = torch.tensor([[[[0.5, 0.5], [0.1, 0.9]]]], dtype=torch.float64)
    target = torch.tensor([[[[0.6, 0.3], [0.1, 0.8]]]], dtype=torch.float64)
    mask = torch.tensor([[[True, True]]])
    assert position_loss(predicted, target, mask, count_offset=0).item() == pytest.approx(0.2)
    empty = torch.tensor([[[False, False]]])
    assert position_loss(predicted, target, empty, count_offset=0).item() == 0.0  # not 0/0
    logits = torch.zeros(1, 1, 2, 3, dtype=torch.float64)
    visible = torch.tensor([[[True, False]]])
    v2 = focal_visibility_loss(logits, visible, mask)
    v1 = focal_visibility_loss(logits, visible, mask, count_offset=0)
    torch.testing.assert_close(v1, v2 * 3 / 2)


def _output(layers: int, positions: torch.Tensor, logits: torch.Tensor, updated=None):
    logit_positions = torch.logit(positions)
    boxes = torch.cat((logit_positions, torch.zeros_like(logit_positions)), -1)
    stack = boxes.expand(layers, *boxes.shape).clone()
    return TrackOutput(
        positions,
        logits,
        stack,
        logits.expand(layers, *logits.shape).clone(),
        None if updated is None else stack + updated,
    )


def test_masks_start_frame_and_outside_image_rule():
    # one clip, T = 3, N = 2; point 0 starts at frame 0, point 1 at frame 1
    predicted = torch.full((1, 3, 2, 2), 0.5, dtype=torch.float64)
    target = torch.tensor(
        [[[[0.5, 0.5], [0.5, 0.5]], [[1.0, 0.0], [0.9, 0.5]], [[1.2, 0.5], [0.5, -0.1]]]],
        dtype=torch.float64,
    )
    logits = torch.zeros(1, 3, 2, 3, dtype=torch.float64)
    targets = Targets(target, torch.ones(1, 3, 2, dtype=torch.bool), torch.tensor([[0, 1]]))
    out = tracking_loss(_output(2, predicted, logits), targets, LossWeights())
    # U = {(1,0), (2,0), (2,1)}; (2,0) and (2,1) lie outside; (1,0) sits on the border
    assert out.terms["position_1"].item() == pytest.approx((0.5 + 0.5) / 2)
    focal = 2 * _focal_by_hand(0.0, 0) + _focal_by_hand(0.0, 1)
    assert out.terms["visibility_1"].item() == pytest.approx(3 * focal / 4)
    assert out.total.item() == pytest.approx(5 * 2 * 0.5 + 3 * focal / 4)


def test_updated_positions_switch_and_batch_mean():
    predicted = torch.full((2, 2, 1, 2), 0.25, dtype=torch.float64)
    target = torch.full((2, 2, 1, 2), 0.5, dtype=torch.float64)
    target[1] = 0.75
    logits = torch.zeros(2, 2, 1, 3, dtype=torch.float64)
    targets = Targets(target, torch.ones(2, 2, 1, dtype=torch.bool), torch.zeros(2, 1).long())
    shift = torch.zeros(1, 2, 2, 1, 4, dtype=torch.float64)
    output = _output(1, predicted, logits, updated=shift)
    on = tracking_loss(output, targets, LossWeights())
    off = tracking_loss(output, targets, LossWeights(supervise_updated_positions=False))
    # per clip: |Δ| summed over x, y, divided by 1 + 1; then the mean of the two clips
    assert on.terms["position_0"].item() == pytest.approx((0.5 / 2 + 1.0 / 2) / 2)
    assert on.terms["updated_position_0"].item() == on.terms["position_0"].item()
    assert on.total.item() - off.total.item() == pytest.approx(5 * on.terms["position_0"].item())


OFFICIAL_TERMS = {
    "pt_full_loss_ce": "visibility_4",
    "pt_full_loss_bbox": "position_4",
    "pt_full_loss_xy": "position_4",
    "pt_full_ca_loss_ce": "visibility_4",
    "pt_full_ca_loss_bbox": "updated_position_4",
    "pt_full_ca_loss_xy": "updated_position_4",
}
for _layer in range(4):
    for _official, _ours in list(OFFICIAL_TERMS.items()):
        OFFICIAL_TERMS[f"{_official}_{_layer}"] = _ours.replace("_4", f"_{_layer}")


@pytest.fixture(scope="module")
def official_run(official_checkpoint):
    golden = load_golden("loss_v2")
    model = taptr.load_checkpoint(official_checkpoint).train()
    model.window_dropout = 0.0
    batch = ClipBatch(
        torch.from_numpy(golden["in_video_u8"]),
        torch.from_numpy(golden["gt_xy_norm"]).transpose(0, 1)[None],
        torch.from_numpy(~golden["gt_occluded"]).transpose(0, 1)[None],
        torch.from_numpy(golden["in_query_t"])[None],
    )
    output = TrainingForward(model)(*batch)
    loss = tracking_loss(output, batch_targets(batch), LossWeights())
    loss.total.backward()
    return golden, model, batch, output, loss


def test_queries_are_the_official_inputs(official_run):
    golden, _, batch, _, _ = official_run
    queries = batch_queries(batch)
    assert torch.equal(queries.positions[0], torch.from_numpy(golden["in_query_xy_norm"]))
    assert torch.equal(queries.start_visible[0], torch.from_numpy(golden["in_query_label"] == 1))


def test_every_official_loss_term_and_total(official_run):
    golden, _, _, output, loss = official_run
    stored = dict(zip(golden["loss_names"].tolist(), golden["loss_values"], strict=True))
    compared = 0
    for name, value in stored.items():
        if "_hw" in name:
            # logged only: L1 of the unsupervised (w, h) against the official 0.01 "size"
            layer = int(name[-1]) if name[-1].isdigit() else 4
            source = output.layer_updated_positions if "_ca_" in name else output.layer_positions
            mask = torch.from_numpy(golden["loss_mask_location"]).T[None]
            wh = source[layer, ..., 2:].sigmoid().double()
            ours = position_loss(wh, torch.full_like(wh, 0.01), mask).item()
        else:
            ours = loss.terms[OFFICIAL_TERMS[name]].item()
        assert ours == pytest.approx(value, rel=1e-5), name
        compared += 1
    assert compared == 40
    assert loss.total.item() == pytest.approx(float(golden["loss_total"]), rel=1e-5)


def test_gradient_norms_match_official(official_run):
    golden, model, _, _, _ = official_run
    names = golden["grad_param_names"].tolist()
    renamed, _ = convert_state_dict({n: torch.tensor(i) for i, n in enumerate(names)})
    ours_by_index = {int(index): name for name, index in renamed.items()}
    parameters = dict(model.named_parameters())
    assert len(parameters) == len(names)
    norms = np.array(
        [parameters[ours_by_index[i]].grad.double().norm().item() for i in range(len(names))]
    )
    expected = golden["grad_norm"]
    zero = expected == 0  # the intermediate visibility heads: their terms have weight 0
    assert zero.sum() == 8 and np.all(norms[zero] == 0)
    np.testing.assert_allclose(norms[~zero], expected[~zero], rtol=1e-3)


def test_v3_supervises_positions_where_visible_only():
    predicted = torch.full((1, 3, 2, 2), 0.5, dtype=torch.float64)
    target = torch.full((1, 3, 2, 2), 0.25, dtype=torch.float64)
    visible = torch.tensor([[[True, True], [True, False], [False, True]]])
    logits = torch.zeros(1, 3, 2, 3, dtype=torch.float64)
    targets = Targets(target, visible, torch.tensor([[0, 0]]))
    v2 = tracking_loss(_output(1, predicted, logits), targets, LossWeights())
    v3 = tracking_loss(
        _output(1, predicted, logits), targets, LossWeights(occluded_positions=False)
    )
    # U holds frames 1 and 2 of both points; v3 keeps the two visible ones
    assert v2.terms["position_0"].item() == pytest.approx(4 * 0.5 / 5)
    assert v3.terms["position_0"].item() == pytest.approx(2 * 0.5 / 3)
    assert v3.terms["visibility_0"].item() == v2.terms["visibility_0"].item()
