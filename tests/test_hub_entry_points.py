"""torch.hub entry points (``hubconf.py``) loaded from the local checkout, offline."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from taptr.api.predictor import Predictor
from taptr.config import PRESETS
from taptr.weights import registry
from taptr.weights.checkpoint import save_checkpoint

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def offline(monkeypatch, tmp_path):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub-cache"))


def hub_entry_points() -> list[str]:
    module = torch.hub._import_module("hubconf", str(ROOT / "hubconf.py"))
    return sorted(
        name for name in dir(module) if callable(getattr(module, name)) and not name.startswith("_")
    )


def test_entry_points():
    expected = {"taptrv2", "taptr_small_synthetic"} | (
        {"taptrv1"} if "taptrv1" in PRESETS else set()
    )
    assert set(hub_entry_points()) == expected


def test_bundled_model_loads_from_the_local_repository(tmp_path, tiny_model, monkeypatch):
    weights = save_checkpoint(tiny_model, tmp_path / "taptr-small-synthetic.pth")
    monkeypatch.setattr(registry, "bundled_path", lambda name: weights)
    predictor = torch.hub.load(str(ROOT), "taptr_small_synthetic", source="local", device="cpu")
    assert isinstance(predictor, Predictor)
    assert predictor.device == torch.device("cpu")
    for key, value in tiny_model.state_dict().items():
        torch.testing.assert_close(predictor.model.state_dict()[key], value, rtol=0, atol=0)


def test_taptrv2_entry_point_reads_the_hub_cache(
    tmp_path, official_checkpoint, official_state_dict, monkeypatch
):
    pytest.importorskip("huggingface_hub")
    from huggingface_hub import constants

    from tests.test_hub import place_in_cache

    cache = tmp_path / "hub-cache"
    place_in_cache(cache, "HYeungLee/TAPTR-Series", "taptrv2.pth").symlink_to(official_checkpoint)
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(cache))
    predictor = torch.hub.load(str(ROOT), "taptrv2", source="local", device="cpu")
    # the file in the cache, not a fresh model
    torch.testing.assert_close(
        predictor.model.state_dict()["backbone.body.conv1.weight"],
        official_state_dict["module.backbone.0.body.conv1.weight"],
        rtol=0,
        atol=0,
    )
