"""Weights that are not what their name says (issue 37, item 4).

Named weights know their architecture: another model's file under that name (TAPTRv2 as
TAPTRv3, ResNet-50 as ResNet-18 and back) is refused with what the file is and what was
expected, before any module is built; and ``settings.json`` records the SHA-256 of the
file the weights came from, named or not. Offline: nothing here downloads.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

import taptr
from taptr.config import get_config
from taptr.weights import registry
from taptr.weights.checkpoint import CheckpointError, save_checkpoint
from taptr.weights.identity import architecture_problem, describe, same_architecture

R18_FILE = "TAPTRv3_resnet18_384x512.pth"
R50_FILE = "TAPTRv3_resnet50_512x512.pth"


@pytest.fixture
def weights(monkeypatch, tmp_path):
    """An empty weights folder of our own; downloads disabled."""
    monkeypatch.setenv("TAPTR_OFFLINE", "1")
    monkeypatch.setenv("TAPTR_WEIGHTS_DIR", str(tmp_path))
    return tmp_path


def test_taptrv2_saved_as_taptrv3_official_is_refused(weights, official_checkpoint):
    (weights / R18_FILE).symlink_to(official_checkpoint)
    with pytest.raises(CheckpointError) as raised:
        taptr.from_pretrained("taptrv3-official")
    message = str(raised.value)
    assert str(weights / R18_FILE) in message
    assert "holds TAPTRv2 (ResNet-50 backbone, C = 256)" in message
    assert "but taptrv3-official is TAPTRv3 (ResNet-18 backbone, C = 256)" in message
    # the same file by its path is what it is: TAPTRv2
    assert taptr.from_pretrained(str(weights / R18_FILE)).config.version == 2


def test_resnet18_saved_as_the_resnet50_model_is_refused(weights, official_v3_checkpoint):
    (weights / R50_FILE).symlink_to(official_v3_checkpoint)
    with pytest.raises(CheckpointError, match=r"holds TAPTRv3 \(ResNet-18.*is TAPTRv3 \(ResNet-50"):
        taptr.Predictor.from_pretrained("taptrv3-r50-official", device="cpu")


def test_resnet50_saved_as_the_resnet18_model_is_refused(weights):
    # a taptr-format TAPTRv3 ResNet-50 (half precision: 75 MB) under the ResNet-18 name
    model = taptr.build_model("taptrv3-r50")
    save_checkpoint(model, weights / R18_FILE, half=True)
    del model
    with pytest.raises(CheckpointError, match=r"holds TAPTRv3 \(ResNet-50.*is TAPTRv3 \(ResNet-18"):
        taptr.from_pretrained("taptrv3-official")


def test_the_same_architecture_with_other_settings_is_accepted():
    released = get_config("taptrv3")
    calibrated = released.replace(visibility_threshold=0.3, context_points=64)
    assert same_architecture(calibrated, released)
    assert architecture_problem(calibrated, "taptrv3-official", "taptrv3") is None
    assert not same_architecture(get_config("taptrv3-r50"), released)
    assert describe(get_config("taptrv2")) == "TAPTRv2 (ResNet-50 backbone, C = 256)"


def test_every_named_weights_entry_names_a_known_architecture():
    for entry in [*registry.WEIGHTS.values(), *registry.MANUAL.values()]:
        if entry.preset in taptr.config.PRESETS:
            assert describe(get_config(entry.preset)).startswith("TAPTR")


def test_settings_record_the_sha256_of_named_weights(tmp_path):
    from taptr.cli.main import main
    from taptr.io.video import write_video

    clip = write_video(tmp_path / "clip.mp4", np.full((4, 32, 48, 3), 90, np.uint8), fps=4)
    out = tmp_path / "out"
    argv = ["track", str(clip), "--grid", "2", "--checkpoint", "taptr-small-synthetic"]
    assert main([*argv, "--out", str(out)]) == 0
    recorded = json.loads((out / "settings.json").read_text())
    assert recorded["model"] == "taptr-small-synthetic"
    assert recorded["model_sha256"] == registry.file_sha256(
        registry.bundled_path("taptr-small-synthetic")
    )
