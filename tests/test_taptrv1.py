"""TAPTR (v1): parameter count, checkpoint loading, golden outputs, cost volume, switches."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

import taptr
from taptr.config import taptrv1, tiny
from taptr.model.taptr import normalize_frames
from taptr.model.v1 import CostVolume
from taptr.official.convert import convert_state_dict
from tests.helpers import FIXTURES, load_golden, tiny_v1


def test_paper_v1_counts_41_068_522_parameters():
    model = taptr.build_model("taptrv1")
    assert sum(p.numel() for p in model.parameters()) == 41_068_522


def test_fabricated_v1_state_dict_loads_strictly():
    state = {}
    for line in (FIXTURES / "official-v1-state-dict.txt").read_text().splitlines():
        key, dims = line.split(" ", 1)
        shape = [int(d) for d in dims.strip("[]").split(",") if d.strip()]
        state["module." + key] = torch.zeros(shape)
    assert len(state) == 628
    converted, dropped = convert_state_dict(state)
    assert len(dropped) == 48
    model = taptr.build_model("taptrv1")
    assert set(converted) == set(model.state_dict())
    model.load_state_dict(converted, strict=True)


@pytest.fixture(scope="module")
def official_v1(official_v1_checkpoint):
    model = taptr.load_checkpoint(official_v1_checkpoint)
    assert model.config == taptrv1()
    return model


def _inputs(golden, dtype=torch.float32):
    video = normalize_frames(torch.from_numpy(golden["in_video_u8"]).float() / 255).to(dtype)
    return (
        video,
        torch.from_numpy(golden["in_query_t"]),
        torch.from_numpy(golden["in_query_xy_norm"]).to(dtype),
        torch.from_numpy(golden["in_query_label"]),
    )


def _point_major(x: torch.Tensor) -> np.ndarray:
    return x.transpose(0, 1).double().numpy()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_v1_golden_outputs(official_v1, dtype):
    golden = load_golden("v1_small")
    model = official_v1 if dtype == torch.float32 else copy.deepcopy(official_v1).double()
    out = taptr.official_forward(model, *_inputs(golden, dtype))
    prefix, tolerance = ("", 3e-5) if dtype == torch.float32 else ("f64_", 1e-6)
    positions = _point_major(out["positions"])
    logits = _point_major(out["visibility_logits"])
    assert np.abs(positions - golden[f"{prefix}out_pred_xy_norm"]).max() <= tolerance
    assert np.abs(logits - golden[f"{prefix}out_vis_logits"]).max() <= tolerance
    assert len(out["layers"]) == 6
    assert all(layer["updated_positions"] is None for layer in out["layers"])
    if dtype == torch.float32:
        for index, layer in enumerate(out["layers"]):
            error = np.abs(_point_major(layer["positions"]) - golden["layers_pred_xy"][index])
            assert error.max() <= 3e-5


def test_cost_volume_sampling_by_hand():
    volume = CostVolume(d_model=4, num_levels=2, radius=1)
    # level 0: 3×5 map with value 10·row + column; level 1: 2×3 map with value 100 + column
    level0 = (10 * torch.arange(3.0)[:, None] + torch.arange(5.0)).view(1, 1, 3, 5)
    level1 = (100 + torch.arange(3.0)).expand(2, 3).reshape(1, 1, 2, 3)
    position = torch.tensor([[[0.5, 0.25]]])  # x·(H0 − 1) = 1.0, y·(W0 − 1) = 1.0 (swapped)
    samples = volume.sample([level0, level1], position)[0, 0]
    assert samples.shape == (2 * 9,)
    # level 0, x-offset major: (x, y) = (0,0), (0,1), (0,2), (1,0), ...; value 10·y + x
    expected0 = [10 * y + x for x in (0, 1, 2) for y in (0, 1, 2)]
    assert samples[:9].tolist() == expected0
    # level 1: centre (0.5, 0.5); columns clamp to [0, 2] (border), value 100 + x
    expected1 = [100 + min(max(x, 0), 2) for x in (-0.5, 0.5, 1.5) for _ in (0, 1, 2)]
    assert samples[9:].tolist() == expected1


def test_cost_volume_correlation_is_a_scaled_dot_product(generator):
    volume = CostVolume(d_model=4, num_levels=1, radius=1)
    memory = torch.randn(2, 6, 4, generator=generator)  # 2 frames, a 2×3 level
    content = torch.randn(2, 5, 4, generator=generator)
    (maps,) = volume.prepare(memory, [(2, 3)], content)
    weight = volume.fmap_mappers[0].weight.view(4, 4)
    mapped = memory @ weight.T + volume.fmap_mappers[0].bias
    expected = volume.query_proj(content) @ mapped.transpose(1, 2) / 2.0
    torch.testing.assert_close(maps, expected.view(2, 5, 2, 3))


def _run(config, video, starts, xy):
    torch.manual_seed(0)
    model = taptr.build_model(config).eval()
    with torch.no_grad():  # random, non-trivial values for the zero-initialised parts
        for param in model.parameters():
            if not param.any():
                param.normal_(0, 0.1)
    return model, taptr.official_forward(model, video, starts, xy)["positions"]


@pytest.mark.parametrize(
    "switch", [dict(point_attention=False), dict(temporal_attention=False), dict(cost_volume=False)]
)
def test_table1_switches_change_outputs(generator, switch):
    video = torch.randn(1, 12, 3, 64, 64, generator=generator)
    starts, xy = torch.tensor([0, 2, 5]), torch.rand(3, 2, generator=generator)
    full_model, full = _run(tiny_v1(), video, starts, xy)
    ablated_model, ablated = _run(tiny_v1(**switch), video, starts, xy)
    assert not torch.allclose(full, ablated, atol=1e-4)
    assert sum(p.numel() for p in ablated_model.parameters()) < sum(
        p.numel() for p in full_model.parameters()
    )


def test_memory_efficient_mode(generator):
    video = torch.randn(1, 16, 3, 64, 64, generator=generator)
    xy = torch.rand(3, 2, generator=generator)
    early = torch.tensor([0, 3, 7])
    _, normal = _run(tiny_v1(), video, early, xy)
    _, efficient = _run(tiny_v1(memory_efficient=True), video, early, xy)
    torch.testing.assert_close(normal, efficient)  # every point starts before frame 8
    late = torch.tensor([0, 3, 11])
    _, normal = _run(tiny_v1(), video, late, xy)
    _, efficient = _run(tiny_v1(memory_efficient=True), video, late, xy)
    assert not torch.allclose(normal, efficient, atol=1e-4)


def test_version_constraints():
    with pytest.raises(ValueError, match="version 1"):
        tiny().replace(cost_volume=True)
    with pytest.raises(ValueError, match="version 1 uses"):
        tiny().replace(version=1)
