"""Model-level behaviour on the tiny preset: shapes, gradients, query frames, ablations."""

from __future__ import annotations

import pytest
import torch

import taptr
from taptr.config import tiny
from taptr.geometry import clamp_to_unit
from taptr.model.sliding_window import run_windows
from taptr.model.trajectory import QuerySet
from taptr.runtime.frames import EncodedFrames, PrecomputedFrames


def _video(frames: int, generator: torch.Generator, batch: int = 1, size=(64, 64)) -> torch.Tensor:
    return torch.randn(batch, frames, 3, *size, generator=generator)


def _queries(batch: int, starts: list[int], generator: torch.Generator) -> QuerySet:
    points = len(starts)
    return QuerySet(
        torch.tensor(starts).repeat(batch, 1),
        torch.rand(batch, points, 2, generator=generator) * 0.8 + 0.1,
        torch.ones(batch, points, dtype=torch.bool),
    )


def _track(model, video, queries):
    return run_windows(model, queries, video.shape[1], EncodedFrames(model, video), video.dtype)


def test_output_shapes_and_finite(tiny_model, generator):
    video = _video(24, generator, batch=2)
    out = _track(tiny_model, video, _queries(2, [0, 3, 10, 23], generator))
    assert out.positions.shape == (2, 24, 4, 2)
    assert out.visibility_logits.shape == (2, 24, 4, 3)
    assert out.layer_positions.shape == (5, 2, 24, 4, 4)
    assert out.layer_visibility_logits.shape == (5, 2, 24, 4, 3)
    assert out.layer_updated_positions.shape == (5, 2, 24, 4, 4)
    assert (
        torch.isfinite(out.layer_positions).all()
        and torch.isfinite(out.layer_visibility_logits).all()
    )


def test_every_parameter_receives_a_gradient(generator):
    torch.manual_seed(0)
    model = taptr.build_model("tiny").train()
    with (
        torch.no_grad()
    ):  # zero-initialised matrices (offsets, last head layers) block gradients at init
        for param in model.parameters():
            if param.dim() > 1 and not param.any():
                param.normal_(0, 0.02)
    video = _video(12, generator)  # two windows: the content hand-over is exercised
    out = run_windows(
        model,
        _queries(1, [0, 2, 5], generator),
        12,
        PrecomputedFrames(model.encode(video)),
        video.dtype,
    )
    loss = (
        out.layer_positions.sigmoid().sum()
        + out.layer_visibility_logits.sum()
        + out.layer_updated_positions.sigmoid().sum()
    )
    loss.backward()
    missing = [
        n for n, p in model.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0
    ]
    assert missing == []


def test_start_frame_keeps_query_and_earlier_frames_keep_initial_state(tiny_model, generator):
    video = _video(16, generator)
    queries = QuerySet(
        torch.tensor([[0, 6, 15]]),
        torch.tensor([[[0.0, 1.0], [0.3, 0.7], [0.5, 0.5]]]),
        torch.tensor([[True, False, True]]),
    )
    out = _track(tiny_model, video, queries)
    for point, start in enumerate([0, 6, 15]):
        expected_xy = clamp_to_unit(queries.positions[0, point])
        for frame in range(start + 1):
            torch.testing.assert_close(
                out.positions[0, frame, point], expected_xy, atol=1e-7, rtol=0
            )
            one_hot = torch.tensor(
                [0.0, 1.0, 0.0] if queries.start_visible[0, point] else [0.0, 0.0, 1.0]
            )
            assert torch.equal(out.visibility_logits[0, frame, point], one_hot)
        if start < 15:
            assert not torch.allclose(out.positions[0, start + 1, point], expected_xy)


def test_batched_equals_one_video_at_a_time(tiny_model, generator):
    video = _video(12, generator, batch=2)
    queries = QuerySet(
        torch.tensor([[0, 4, 9], [2, 2, 0]]),
        torch.rand(2, 3, 2, generator=generator),
        torch.ones(2, 3, dtype=torch.bool),
    )
    both = _track(tiny_model, video, queries)
    for b in range(2):
        single = _track(tiny_model, video[b : b + 1], QuerySet(*(q[b : b + 1] for q in queries)))
        torch.testing.assert_close(both.positions[b], single.positions[0], atol=1e-5, rtol=0)
        torch.testing.assert_close(
            both.visibility_logits[b], single.visibility_logits[0], atol=1e-5, rtol=0
        )


def test_points_not_yet_started_do_not_affect_others(tiny_model, generator):
    video = _video(24, generator)
    base = QuerySet(
        torch.tensor([[0, 1]]),
        torch.tensor([[[0.2, 0.3], [0.6, 0.6]]]),
        torch.ones(1, 2, dtype=torch.bool),
    )
    extra = QuerySet(
        torch.tensor([[0, 1, 20]]),
        torch.tensor([[[0.2, 0.3], [0.6, 0.6], [0.5, 0.4]]]),
        torch.ones(1, 3, dtype=torch.bool),
    )
    a, b = _track(tiny_model, video, base), _track(tiny_model, video, extra)
    # frames 0..15 are last written by windows that end before frame 20
    torch.testing.assert_close(a.positions[0, :16], b.positions[0, :16, :2], atol=1e-5, rtol=0)
    assert not torch.allclose(a.positions[0, 20:], b.positions[0, 20:, :2], atol=1e-4)


def test_lazy_encoding_equals_encoding_all_frames(tiny_model, generator):
    video = _video(20, generator)
    queries = _queries(1, [0, 5, 13], generator)
    lazy = _track(tiny_model, video, queries)
    with torch.no_grad():
        full = run_windows(
            tiny_model, queries, 20, PrecomputedFrames(tiny_model.encode(video)), video.dtype
        )
    # per-frame and batched convolutions round differently: compare at float32 noise level
    torch.testing.assert_close(lazy.layer_positions, full.layer_positions, atol=1e-4, rtol=0)


@pytest.mark.parametrize("frames", [1, 3, 7])
def test_videos_shorter_than_a_window(tiny_model, generator, frames):
    video = _video(frames, generator)
    out = taptr.official_forward(
        tiny_model, video, torch.tensor([0, frames - 1]), torch.tensor([[0.4, 0.5], [0.5, 0.5]])
    )
    assert out["positions"].shape == (frames, 2, 2)
    if frames > 1:  # the first point is written after its start frame
        assert not torch.allclose(out["positions"][1:, 0], out["positions"][0, 0])


def test_long_video_content_rule_changes_outputs(generator):
    torch.manual_seed(0)
    model = taptr.build_model("tiny").eval()
    video = _video(50, generator, size=(32, 32))
    queries = _queries(1, [0, 3], generator)
    with torch.no_grad():
        features = PrecomputedFrames(model.encode(video))
        gap_two = run_windows(model, queries, 50, features, video.dtype)  # ⌊50/24⌋ = 2
        model.long_video_frames = 100  # every window pads the content
        every = run_windows(model, queries, 50, features, video.dtype)
    assert torch.allclose(gap_two.positions[:, :8], every.positions[:, :8])  # windows 0-1 agree
    assert not torch.allclose(gap_two.positions, every.positions)


ABLATIONS = {
    "standard_cross_attention": dict(cross_attention="standard"),
    "no_position_update": dict(position_update=False, disentangler=False),
    "no_disentangler": dict(disentangler=False),
    "depth_2": dict(decoder_layers=2),
    "depth_6": dict(decoder_layers=6),
}


@pytest.mark.parametrize("name", list(ABLATIONS))
def test_ablation_switches_change_behaviour(name, generator):
    video = _video(12, generator)
    queries = _queries(1, [0, 4], generator)
    outputs = {}
    for label, config in (("paper", tiny()), (name, tiny().replace(**ABLATIONS[name]))):
        torch.manual_seed(0)
        model = taptr.build_model(config).eval()
        # the ablated parts start at a non-trivial point so that they matter at init
        with torch.no_grad():
            for head in model.decoder.position_heads:
                head.layers[-1].weight.normal_(0, 0.1)
        outputs[label] = (_track(model, video, queries), model)
    (paper, paper_model), (ablated, ablated_model) = outputs["paper"], outputs[name]
    assert ablated.layer_positions.shape[0] == ablated_model.num_layers
    assert not torch.allclose(paper.positions, ablated.positions)
    if name == "no_position_update":
        assert ablated.layer_updated_positions is None
        assert ablated_model.decoder.update_fuser is None
    if name == "standard_cross_attention":
        assert hasattr(ablated_model.decoder.layers[0].cross_attention, "attention_weights")
    if name == "no_disentangler":
        assert ablated_model.decoder.layers[0].position_update.disentangler is None
        assert sum(p.numel() for p in ablated_model.parameters()) < sum(
            p.numel() for p in paper_model.parameters()
        )


def test_official_forward_rejects_bad_inputs(tiny_model):
    video = torch.zeros(1, 8, 3, 32, 32)
    with pytest.raises(ValueError, match="query_frames must lie"):
        taptr.official_forward(tiny_model, video, torch.tensor([8]), torch.tensor([[0.5, 0.5]]))
    with pytest.raises(ValueError, match="NaN"):
        taptr.official_forward(
            tiny_model, video, torch.tensor([0]), torch.tensor([[float("nan"), 0.5]])
        )
    with pytest.raises(ValueError, match=r"\(1, T, 3, H, W\)"):
        taptr.official_forward(tiny_model, video[0], torch.tensor([0]), torch.tensor([[0.5, 0.5]]))
    with pytest.raises(ValueError, match="query_labels"):
        taptr.official_forward(
            tiny_model, video, torch.tensor([0]), torch.tensor([[0.5, 0.5]]), torch.tensor([3])
        )


def test_fast_execution_equals_reference_execution(generator):
    torch.manual_seed(0)
    model = taptr.build_model("tiny").eval()
    assert model.execution.name == "fast"  # the default
    video = _video(20, generator)
    # start frames inside windows give mixed tracked/untracked frames and points
    queries = QuerySet(
        torch.tensor([[0, 3, 6, 9, 13, 19]]),
        torch.rand(1, 6, 2, generator=generator),
        torch.ones(1, 6, dtype=torch.bool),
    )
    fast = _track(model, video, queries)
    reference = _track(model.set_execution("reference"), video, queries)
    assert model.execution.name == "reference"
    assert not torch.equal(fast.layer_positions, reference.layer_positions)  # really two ways
    # float32 noise of different summation orders, amplified by the random weights
    torch.testing.assert_close(fast.layer_positions, reference.layer_positions, atol=1e-4, rtol=0)
    torch.testing.assert_close(
        fast.layer_visibility_logits, reference.layer_visibility_logits, atol=1e-4, rtol=0
    )
    training = _track(model.set_execution("training"), video, queries)
    torch.testing.assert_close(
        training.layer_positions, reference.layer_positions, atol=1e-4, rtol=0
    )
    with pytest.raises(ValueError, match="unknown execution"):
        model.set_execution("turbo")
