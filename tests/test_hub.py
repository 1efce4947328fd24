"""Name resolution: published weights through a temporary Hugging Face cache, offline.

Nothing here touches the network: offline mode is on in every test, and the cache is a
temporary folder laid out as the Hub lays it out (``models--OWNER--NAME/refs/main`` holding
a commit, the file under ``snapshots/<commit>/``).
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
from pathlib import Path

import pytest
import torch

import taptr
from taptr.config import PRESETS
from taptr.weights import registry
from taptr.weights.checkpoint import CheckpointError, save_checkpoint

pytest.importorskip("huggingface_hub")

COMMIT = "0123456789abcdef0123456789abcdef01234567"


@pytest.fixture(autouse=True)
def offline(monkeypatch, tmp_path):
    """Offline mode, an empty cache of our own, and no network connection at all."""

    def refuse(*args, **kwargs):
        raise AssertionError("a test tried to open a network connection")

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub-cache"))
    monkeypatch.setattr(socket.socket, "connect", refuse)
    return tmp_path / "hub-cache"


def place_in_cache(cache: Path, repo_id: str, filename: str) -> Path:
    """The path where the Hub cache keeps ``filename`` of ``repo_id`` at our fake commit."""
    repo = cache / f"models--{repo_id.replace('/', '--')}"
    (repo / "refs").mkdir(parents=True, exist_ok=True)
    (repo / "refs" / "main").write_text(COMMIT)
    path = repo / "snapshots" / COMMIT / filename
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


@pytest.fixture
def cached_taptrv2(offline, official_checkpoint) -> Path:
    """The seed-1 TAPTRv2 weights as taptrv2.pth in the cache (a hard link: tests delete it)."""
    path = place_in_cache(offline, "HYeungLee/TAPTR-Series", "taptrv2.pth")
    try:
        os.link(official_checkpoint, path)
    except OSError:  # another file system
        shutil.copyfile(official_checkpoint, path)
    return path


def test_registry_names():
    assert {"taptrv2-official", "taptrv1-official", "taptr-small-synthetic"} <= set(
        registry.known_names()
    )
    assert set(PRESETS) <= set(registry.known_names())
    entry = registry.WEIGHTS["taptrv2-official"]
    assert (entry.repo_id, entry.filename, entry.preset) == (
        "HYeungLee/TAPTR-Series",
        "taptrv2.pth",
        "taptrv2",
    )
    assert entry.url == "https://huggingface.co/HYeungLee/TAPTR-Series/resolve/main/taptrv2.pth"
    assert registry.WEIGHTS["taptrv1-official"].filename == "taptrv1.pth"


def test_cached_weights_resolve_offline(offline, cached_taptrv2, official_state_dict):
    assert registry.weights_path("taptrv2-official", cache_dir=offline) == cached_taptrv2
    model = taptr.from_pretrained("taptrv2-official", cache_dir=offline)
    assert not model.training and model.config.d_model == 256
    torch.testing.assert_close(
        model.state_dict()["backbone.body.conv1.weight"],
        official_state_dict["module.backbone.0.body.conv1.weight"],
        rtol=0,
        atol=0,
    )


def test_another_model_cached_as_taptrv2_is_refused_with_what_it_is(offline, tiny_model):
    save_checkpoint(tiny_model, place_in_cache(offline, "HYeungLee/TAPTR-Series", "taptrv2.pth"))
    with pytest.raises(CheckpointError) as raised:
        taptr.from_pretrained("taptrv2-official", cache_dir=offline)
    message = str(raised.value)
    assert "holds TAPTRv2 (small convolutional backbone, C = 32)" in message
    assert "taptrv2-official is TAPTRv2 (ResNet-50 backbone, C = 256)" in message


def test_default_cache_comes_from_the_environment(cached_taptrv2, monkeypatch):
    # huggingface_hub reads HF_HUB_CACHE at import; point its default at our folder
    from huggingface_hub import constants

    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(cached_taptrv2.parents[3]))
    predictor = taptr.Predictor.from_pretrained("taptrv2-official", device="cpu")
    assert predictor.model.config.d_model == 256


def test_missing_weights_say_what_to_download_and_where(offline):
    with pytest.raises(FileNotFoundError) as raised:
        taptr.from_pretrained("taptrv2-official", cache_dir=offline)
    message = str(raised.value)
    assert "HF_HUB_OFFLINE=1" in message
    assert "https://huggingface.co/HYeungLee/TAPTR-Series/resolve/main/taptrv2.pth" in message
    assert 'taptr.from_pretrained("/path/to/taptrv2.pth")' in message
    assert str(offline / "models--HYeungLee--TAPTR-Series") in message
    assert not offline.exists() or not any(offline.rglob("*.pth"))  # nothing was fetched


def test_sha256_is_checked_when_registered(offline, cached_taptrv2, monkeypatch):
    entry = registry.WEIGHTS["taptrv2-official"]
    good = registry.file_sha256(cached_taptrv2)
    monkeypatch.setitem(
        registry.WEIGHTS, "taptrv2-official", entry.__class__(**{**vars(entry), "sha256": good})
    )
    assert registry.weights_path("taptrv2-official", cache_dir=offline) == cached_taptrv2
    monkeypatch.setitem(
        registry.WEIGHTS, "taptrv2-official", entry.__class__(**{**vars(entry), "sha256": "0" * 64})
    )
    with pytest.raises(CheckpointError, match="SHA-256"):
        registry.weights_path("taptrv2-official", cache_dir=offline)


def test_taptrv1_resolves_its_file_and_a_bad_one_is_moved_aside(offline, caplog):
    path = place_in_cache(offline, "HYeungLee/TAPTR-Series", "taptrv1.pth")
    path.write_bytes(b"not the weights: cut short")
    with caplog.at_level(logging.WARNING), pytest.raises(FileNotFoundError, match=r"taptrv1\.pth"):
        registry.weights_path("taptrv1-official", cache_dir=offline)
    aside = path.with_name("taptrv1.pth.rejected")
    assert not path.exists() and aside.read_bytes() == b"not the weights: cut short"
    lines = [r.getMessage() for r in caplog.records if "moved aside" in r.getMessage()]
    assert len(lines) == 1 and "a transfer cut short" in lines[0] and str(aside) in lines[0]


@pytest.mark.skipif("taptrv1" not in PRESETS, reason="no TAPTR v1 in this taptr")
def test_taptrv1_official_loads_as_v1(offline, official_v1_checkpoint):
    place_in_cache(offline, "HYeungLee/TAPTR-Series", "taptrv1.pth").symlink_to(
        official_v1_checkpoint
    )
    model = taptr.from_pretrained("taptrv1-official", cache_dir=offline)
    assert model.config.version == 1 and not model.training


def test_taptrv1_without_its_preset_is_not_supported_yet(offline, monkeypatch):
    place_in_cache(offline, "HYeungLee/TAPTR-Series", "taptrv1.pth").write_bytes(b"x")
    monkeypatch.delitem(PRESETS, "taptrv1", raising=False)
    with pytest.raises(NotImplementedError, match="TAPTR v1 is not supported yet"):
        taptr.from_pretrained("taptrv1-official", cache_dir=offline)


def test_paths_and_presets_still_resolve(tmp_path, tiny_model, caplog):
    path = save_checkpoint(tiny_model, tmp_path / "model.pth")
    assert registry.resolve_model(path).config.d_model == 32
    assert registry.resolve_model("tiny").config.d_model == 32
    assert "UNTRAINED" in caplog.text
    with pytest.raises(FileNotFoundError, match="taptrv2-official"):
        registry.resolve_model("no-such-model")


def test_offline_flag_is_read_at_call_time(monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "0")
    from huggingface_hub import constants

    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", False)
    assert not registry.hub_offline()
    monkeypatch.setenv("HF_HUB_OFFLINE", "yes")
    assert registry.hub_offline()
