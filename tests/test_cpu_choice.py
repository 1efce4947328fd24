"""The CPU execution's products and frame layout, measured once and remembered."""

from __future__ import annotations

import pytest
import torch

import taptr
from taptr.model.execution import CHANNELS_LAST_MIN_PIXELS
from taptr.model.ops import dense
from taptr.runtime import cpu_choice
from taptr.runtime.cpu_choice import choose_cpu_execution, time_layouts, time_products
from taptr.runtime.measured_file import read_choices

pytestmark = [
    pytest.mark.cpu,
    pytest.mark.skipif(not dense.onednn_available(), reason="oneDNN inner products are x86-only"),
]

LARGE = (192, 192)  # at the channels-last threshold
assert LARGE[0] * LARGE[1] >= CHANNELS_LAST_MIN_PIXELS


@pytest.fixture
def model():
    torch.manual_seed(0)
    return taptr.build_model("tiny").eval()


@pytest.fixture
def measured_file(tmp_path, monkeypatch):
    path = tmp_path / "measured.json"
    monkeypatch.setenv("TAPTR_MEASURED", str(path))
    return path


def _fake(monkeypatch, products: dict[bool, float], layouts: dict[bool, float]) -> list[str]:
    timed: list[str] = []

    def fake_products(model):
        timed.append("products")
        return products

    def fake_layouts(model, size):
        timed.append("layout")
        return layouts

    monkeypatch.setattr(cpu_choice, "time_products", fake_products)
    monkeypatch.setattr(cpu_choice, "time_layouts", fake_layouts)
    return timed


def test_the_faster_setting_wins_and_is_remembered(model, measured_file, monkeypatch):
    timed = _fake(monkeypatch, {True: 2.0, False: 1.0}, {True: 2.0, False: 1.0})
    execution = choose_cpu_execution(model, LARGE)
    assert not execution.onednn_linear and not execution.channels_last  # BLAS, plain frames
    assert model.execution is execution and execution.kernel == "gather"  # the rest is kept
    assert timed == ["products", "layout"] and len(read_choices(measured_file).choices) == 2
    again = taptr.build_model("tiny").eval()
    assert choose_cpu_execution(again, LARGE) == execution
    assert timed == ["products", "layout"]  # read, not measured


def test_the_executions_own_setting_stays_unless_clearly_slower(model, measured_file, monkeypatch):
    timed = _fake(monkeypatch, {True: 1.0, False: 0.99}, {True: 1.0, False: 0.99})
    execution = choose_cpu_execution(model, LARGE)
    assert execution.onednn_linear and execution.channels_last
    assert timed == ["products", "layout"]


def test_small_frames_and_other_executions_measure_nothing(model, measured_file, monkeypatch):
    timed = _fake(monkeypatch, {True: 2.0, False: 1.0}, {True: 2.0, False: 1.0})
    choose_cpu_execution(model, (64, 64))  # below the threshold: the layout is not asked
    assert timed == ["products"]
    reference = taptr.build_model("tiny", execution="reference").eval()
    assert choose_cpu_execution(reference, LARGE) == reference.execution  # nothing to choose
    assert timed == ["products"]
    monkeypatch.setattr(cpu_choice, "bfloat16_mode", lambda: True)  # only oneDNN has bfloat16
    fresh = taptr.build_model("tiny").eval()
    measured_file.unlink()
    assert choose_cpu_execution(fresh, (64, 64)).onednn_linear
    assert timed == ["products"]


def test_the_timers_time_both_settings_and_restore_the_execution(model):
    own = model.execution
    assert set(time_products(model)) == {True, False}
    assert set(time_layouts(model, (64, 80))) == {True, False}
    assert model.execution is own


def test_a_cpu_predictor_runs_what_was_measured(model, measured_file, monkeypatch):
    from taptr.api.predictor import Predictor

    _fake(monkeypatch, {True: 2.0, False: 1.0}, {True: 2.0, False: 1.0})
    predictor = Predictor(model, device="cpu", frames_per_call=1)
    assert not predictor.model.execution.onednn_linear
    video = torch.randint(0, 256, (1, 6, 3, 48, 64), dtype=torch.uint8)
    result = predictor.track(video, torch.tensor([[0, 20.0, 20.0]]))
    assert result.tracks.shape == (1, 6, 1, 2) and torch.isfinite(result.tracks).all()
