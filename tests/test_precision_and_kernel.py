"""Autocast, the measured kernel choice and torch.compile: the GPU options, checked on CPU."""

from __future__ import annotations

import argparse
import copy

import numpy as np
import pytest
import torch

import taptr
from taptr.api.online import OnlineTracker
from taptr.api.predictor import Predictor
from taptr.cli.common.model_options import KERNEL_CHOICES, add_model_arguments, load_predictor
from taptr.cli.main import main
from taptr.io.tracks import load_tracks_npz
from taptr.io.video import write_video
from taptr.model.ops import dense
from taptr.runtime import compile as compile_module
from taptr.runtime import kernel_choice, measured
from taptr.runtime.kernel_choice import choose_kernel, time_kernels

QUERIES = torch.tensor([[0, 10.0, 20.0], [3, 40.0, 30.0], [5, 70.0, 50.0]])

pytestmark = pytest.mark.cpu


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return taptr.build_model("tiny")


@pytest.fixture(scope="module")
def video():
    generator = torch.Generator().manual_seed(1)
    return torch.randint(0, 256, (1, 10, 3, 64, 80), dtype=torch.uint8, generator=generator)


def _linear_output_types(model: torch.nn.Module) -> tuple[set[torch.dtype], list]:
    seen: set[torch.dtype] = set()
    hooks = [
        m.register_forward_hook(lambda _m, _i, out: seen.add(out.dtype))
        for m in model.modules()
        if isinstance(m, torch.nn.Linear)
    ]
    return seen, hooks


def test_float16_autocast_runs_matrix_products_in_half_and_stays_close(model, video):
    reference = Predictor(copy.deepcopy(model), device="cpu").track(video, QUERIES)
    predictor = Predictor(copy.deepcopy(model), device="cpu", autocast=torch.float16)
    seen, hooks = _linear_output_types(predictor.model)
    result = predictor.track(video, QUERIES)
    for hook in hooks:
        hook.remove()
    assert seen == {torch.float16}  # every linear layer ran in the half type
    assert next(predictor.model.parameters()).dtype == torch.float32  # weights untouched
    assert result.tracks.dtype == torch.float32
    difference = (result.tracks - reference.tracks).abs().max().item()
    assert 0 < difference < 3.0  # pixels of an 80 × 64 video: rounded, not broken


def _count_bfloat16_products(monkeypatch) -> list[int]:
    """Counts the weights `linear` hands to oneDNN in bfloat16."""
    calls = [0]
    original = dense._bfloat16_copy

    def counted(tensor):
        calls[0] += 1
        return original(tensor)

    monkeypatch.setattr(dense, "_bfloat16_copy", counted)
    return calls


@pytest.mark.skipif(not dense.native_bfloat16(), reason="this CPU has no native bfloat16")
def test_bfloat16_on_a_cpu_that_has_it_runs_the_products_in_bfloat16(model, video, monkeypatch):
    reference = Predictor(copy.deepcopy(model), device="cpu").track(video, QUERIES)
    predictor = Predictor(copy.deepcopy(model), device="cpu", autocast=torch.bfloat16)
    calls = _count_bfloat16_products(monkeypatch)
    result = predictor.track(video, QUERIES)
    assert calls[0] > 0
    # the trunk is stored in bfloat16, every other weight stays float32
    assert {p.dtype for p in predictor.model.backbone.parameters()} == {torch.bfloat16}
    rest = [p for n, p in predictor.model.named_parameters() if not n.startswith("backbone.")]
    assert {p.dtype for p in rest} == {torch.float32}
    assert result.tracks.dtype == torch.float32
    difference = (result.tracks - reference.tracks).abs().max().item()
    assert 0 < difference < 3.0  # pixels of an 80 × 64 video: rounded, not broken
    online = OnlineTracker(predictor)  # the online tracker runs in the predictor's context
    state = online.start(num_frames=10, frame_size=(64, 80))
    online.add_queries(state, QUERIES[:1])
    calls[0] = 0
    online.step(state, video[0])
    online.finish(state)
    assert calls[0] > 0


def test_bfloat16_on_a_cpu_without_it_says_so_and_runs_float32(model, video, monkeypatch):
    monkeypatch.setattr("taptr.runtime.runner.native_bfloat16", lambda: False)
    reference = Predictor(copy.deepcopy(model), device="cpu").track(video, QUERIES)
    with pytest.warns(UserWarning, match="no native bfloat16 .*: running float32"):
        predictor = Predictor(copy.deepcopy(model), device="cpu", autocast=torch.bfloat16)
    assert predictor.autocast is None
    assert torch.equal(predictor.track(video, QUERIES).tracks, reference.tracks)


def test_autocast_takes_half_types_only(model):
    with pytest.raises(ValueError, match="autocast must be"):
        Predictor(model, device="cpu", autocast=torch.float32)


def test_time_kernels_times_both_and_restores_the_execution(model):
    fast = copy.deepcopy(model).set_execution("fast")
    ticks = iter(range(100))
    seconds = time_kernels(fast, torch.device("cpu"), repeats=2, clock=lambda: next(ticks))
    assert seconds == {"grid_sample": 1, "gather": 1}  # one tick between start and stop
    assert fast.execution.kernel == "gather"


def test_measure_keeps_the_faster_kernel(model, monkeypatch, tmp_path):
    monkeypatch.setattr(
        kernel_choice, "time_kernels", lambda m, d, input_size: {"grid_sample": 1.0, "gather": 2.0}
    )
    fast = copy.deepcopy(model).set_execution("fast")
    assert choose_kernel(fast, torch.device("cpu"), "measure") == "grid_sample"
    assert fast.execution.kernel == "grid_sample"
    assert fast.execution.grouped_point_attention  # the rest of the execution is kept
    # auto measures on accelerators (the timing is faked: no GPU is used) ...
    monkeypatch.setenv("TAPTR_MEASURED", str(tmp_path / "measured.json"))
    monkeypatch.setattr(measured, "device_name", lambda device: f"fake {device.type}")
    gpu = copy.deepcopy(model).set_execution("fast")
    assert choose_kernel(gpu, torch.device("cuda"), "auto") == "grid_sample"
    # ... once per machine and shape: a second predictor reads the choice ...
    monkeypatch.setattr(
        kernel_choice, "time_kernels", lambda m, d, input_size: pytest.fail("measured")
    )
    again = copy.deepcopy(model).set_execution("fast")
    assert choose_kernel(again, torch.device("cuda"), "auto") == "grid_sample"
    # ... and keeps the execution's kernel on CPU, without measuring
    cpu = copy.deepcopy(model).set_execution("fast")
    assert choose_kernel(cpu, torch.device("cpu"), "auto") == "gather"


def test_a_named_kernel_is_set_and_an_unknown_one_refused(model, video):
    predictor = Predictor(copy.deepcopy(model), device="cpu", kernel="grid_sample")
    assert predictor.model.execution.kernel == "grid_sample"
    gather = Predictor(copy.deepcopy(model), device="cpu", kernel="gather").track(video, QUERIES)
    grid = predictor.track(video, QUERIES)
    torch.testing.assert_close(grid.tracks, gather.tracks, atol=1e-3, rtol=0)
    with pytest.raises(ValueError, match="unknown kernel 'fastest'"):
        Predictor(copy.deepcopy(model), device="cpu", kernel="fastest")


def _model_args(*options: str) -> argparse.Namespace:
    """The model options as the commands parse them."""
    parser = argparse.ArgumentParser()
    add_model_arguments(parser)
    return parser.parse_args(["--checkpoint", "tiny", "--device", "cpu", *options])


def test_the_clis_kernel_choices_are_the_models():
    assert KERNEL_CHOICES == kernel_choice.CHOICES


def test_model_options_reach_the_predictor(monkeypatch, video):
    # bfloat16 as on a CPU that has it, whatever this one has: nothing runs in it here
    monkeypatch.setattr("taptr.runtime.runner.native_bfloat16", lambda: True)
    monkeypatch.setattr("taptr.model.ops.dense.native_bfloat16", lambda: True)
    assert load_predictor(_model_args()).autocast is None
    # a number of frames per call: nothing is timed (in bfloat16, which this CPU may lack)
    predictor = load_predictor(
        _model_args("--dtype", "bfloat16", "--kernel", "grid_sample", "--frames-per-call", "2")
    )
    assert predictor.autocast == torch.bfloat16
    assert predictor.model.execution.kernel == "grid_sample"
    assert predictor.frames_per_call == 2
    for wrong in ("0", "-3", "two"):
        with pytest.raises(SystemExit):
            _model_args("--frames-per-call", wrong)

    compiled = []
    original = compile_module.compile_model

    def eager_compile(model, **kwargs):
        compiled.append((model, copy.deepcopy(model)))
        return original(model, backend="eager")  # traced by dynamo, no code generated

    monkeypatch.setattr(compile_module, "compile_model", eager_compile)
    predictor = load_predictor(_model_args("--compile"))
    [(model, before)] = compiled
    assert model is predictor.model
    plain = Predictor(before, device="cpu")
    # the compiled graph's products run through the BLAS, the eager ones through oneDNN
    # (taptr.model.ops.dense): the same sums in another order, tracks in pixels
    torch.testing.assert_close(
        predictor.track(video, QUERIES).tracks,
        plain.track(video, QUERIES).tracks,
        atol=1e-4,
        rtol=1e-5,
    )


def test_track_with_dtype_and_kernel(model, tmp_path):
    weights = taptr.save_checkpoint(model, tmp_path / "tiny.pth")
    frames = np.full((10, 48, 64, 3), 40, np.uint8)
    for t in range(10):
        frames[t, 16:28, 10 + 2 * t : 22 + 2 * t] = (230, 200, 40)
    clip = write_video(tmp_path / "clip.mp4", frames, fps=10)
    base = ["track", str(clip), "--points", "0,16,22;3,30.5,20", "--checkpoint", str(weights)]
    assert main([*base, "--out", str(tmp_path / "f32")]) == 0
    half = ["--dtype", "float16", "--kernel", "grid_sample"]
    assert main([*base, *half, "--out", str(tmp_path / "f16")]) == 0
    f32 = load_tracks_npz(tmp_path / "f32" / "tracks.npz").tracks
    f16 = load_tracks_npz(tmp_path / "f16" / "tracks.npz").tracks
    assert 0 < np.abs(f32 - f16).max() < 3.0
