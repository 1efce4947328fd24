"""Checkpoint reading, conversion of the official layout, taptr's own format, the CLI."""

from __future__ import annotations

import argparse
import os

import pytest
import torch

import taptr
from taptr.cli.main import main as cli_main
from taptr.official.convert import ConversionError, convert_state_dict
from taptr.weights.checkpoint import (
    CheckpointError,
    UnsafeCheckpointError,
    read_file,
    save_checkpoint,
)
from tests.helpers import FIXTURES


def _fabricated_official() -> dict[str, torch.Tensor]:
    """Zeros in every key and shape of the official key list, with the aliases."""
    state = {}
    for line in (FIXTURES / "official-state-dict.txt").read_text().splitlines():
        key, dims = line.split(" ", 1)
        shape = [int(d) for d in dims.strip("[]").split(",") if d.strip()]
        state["module." + key] = torch.zeros(shape)
    return state


def test_fabricated_official_state_dict_loads_strictly():
    state = _fabricated_official()
    assert len(state) == 614
    converted, dropped = convert_state_dict(state)
    assert len(dropped) == 40
    model = taptr.build_model("taptrv2")
    expected = model.state_dict()
    assert set(converted) == set(expected)  # zero missing, zero unexpected
    assert all(converted[k].shape == expected[k].shape for k in expected)
    result = model.load_state_dict(converted, strict=True)
    assert not result.missing_keys and not result.unexpected_keys


def test_paper_preset_counts_40_040_803_parameters():
    model = taptr.build_model("taptrv2")
    assert sum(p.numel() for p in model.parameters()) == 40_040_803


def test_unknown_official_key_is_named():
    state = _fabricated_official()
    state["module.transformer.decoder.layers.0.mystery.weight"] = torch.zeros(1)
    with pytest.raises(ConversionError, match=r"layers\.0\.mystery\.weight"):
        convert_state_dict(state)


def test_alias_that_differs_from_its_original_is_refused():
    state = _fabricated_official()
    state["module.transformer.decoder.class_embed.0.bias"] = torch.ones(3)
    with pytest.raises(ConversionError, match=r"class_embed\.0\.bias"):
        convert_state_dict(state)


def test_mismatched_checkpoint_report_lists_missing_and_misshaped(tmp_path):
    state = _fabricated_official()
    del state["module.transformer.level_embed"]
    state["module.transformer.decoder.layers.0.linear1.weight"] = torch.zeros(10, 256)
    path = tmp_path / "bad.pth"
    torch.save({"ema_model": state}, path)
    with pytest.raises(CheckpointError) as info:
        taptr.load_checkpoint(path)
    message = str(info.value)
    assert "missing (1): encoder.level_embed" in message
    assert (
        "decoder.layers.0.ffn.layers.0.weight: checkpoint [10, 256] vs model [2048, 256]" in message
    )


class _Payload:
    def __reduce__(self):
        return (os.system, ("echo should-never-run",))


def test_malicious_pickle_is_refused(tmp_path):
    path = tmp_path / "evil.pth"
    torch.save({"ema_model": {}, "payload": _Payload()}, path)
    with pytest.raises(UnsafeCheckpointError, match="system"):
        taptr.load_checkpoint(path)


def test_argparse_namespace_is_allowed(tmp_path, official_state_dict):
    path = tmp_path / "with_args.pth"
    torch.save(
        {"ema_model": official_state_dict, "args": argparse.Namespace(lr=2e-4, dec_layers=5)}, path
    )
    loaded = read_file(path)
    assert loaded["args"].dec_layers == 5
    model = taptr.load_checkpoint(path)
    assert not model.training


def test_official_checkpoint_uses_ema_weights(tmp_path, official_state_dict):
    other = {k: torch.zeros_like(v) for k, v in official_state_dict.items()}
    path = tmp_path / "both.pth"
    torch.save({"model": other, "ema_model": official_state_dict}, path)
    model = taptr.load_checkpoint(path)
    expected = official_state_dict["module.transformer.level_embed"]
    assert torch.equal(model.encoder.level_embed.detach(), expected)


def test_taptr_format_round_trip_prefers_ema(tmp_path):
    torch.manual_seed(0)
    model = taptr.build_model("tiny")
    ema = {k: v + 1 if v.is_floating_point() else v for k, v in model.state_dict().items()}
    path = save_checkpoint(model, tmp_path / "tiny.pth", ema=ema)
    raw = torch.load(path, weights_only=True)
    assert raw["format"] == "taptr" and raw["version"] == 1
    assert raw["config"] == model.config.to_dict()
    loaded = taptr.load_checkpoint(path)
    assert loaded.config == model.config
    for key, value in loaded.state_dict().items():
        assert torch.equal(value, ema[key])


def test_half_precision_checkpoint_loads(tmp_path):
    model = taptr.build_model("tiny")
    path = save_checkpoint(model, tmp_path / "half.pth", half=True)
    loaded = taptr.load_checkpoint(path)
    weight = loaded.encoder.level_embed
    assert weight.dtype == torch.float32
    assert torch.allclose(weight, model.encoder.level_embed.half().float())


@pytest.mark.parametrize("content", [b"", b"not a checkpoint at all", b"PK\x03\x04broken zip"])
def test_garbage_files_give_a_clear_error(tmp_path, content):
    path = tmp_path / "broken.pth"
    path.write_bytes(content)
    with pytest.raises(CheckpointError, match=r"broken\.pth"):
        taptr.load_checkpoint(path)


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        taptr.load_checkpoint(tmp_path / "nope.pth")


def test_unrelated_dict_is_rejected(tmp_path):
    path = tmp_path / "other.pth"
    torch.save({"weights": torch.zeros(3)}, path)
    with pytest.raises(CheckpointError, match="neither a taptr checkpoint"):
        taptr.load_checkpoint(path)


def test_convert_cli(tmp_path, official_checkpoint, capsys):
    out = tmp_path / "converted.pth"
    assert cli_main(["convert", str(official_checkpoint), str(out)]) == 0
    assert "40,040,803 parameters" in capsys.readouterr().out
    converted = taptr.load_checkpoint(out)
    original = taptr.load_checkpoint(official_checkpoint)
    for (name, a), b in zip(
        converted.state_dict().items(), original.state_dict().values(), strict=True
    ):
        assert torch.equal(a, b), name


def test_convert_cli_reports_a_wrong_file_in_one_line(tmp_path, capsys):
    path = tmp_path / "notes.txt"
    path.write_text("hello")
    assert cli_main(["convert", str(path), str(tmp_path / "out.pth")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("taptr convert: error:") and "notes.txt" in err
    assert "Traceback" not in err
    assert not (tmp_path / "out.pth").exists()


def test_convert_keeps_a_calibrated_threshold(tmp_path):
    from taptr.weights.checkpoint import read_visibility_threshold

    source = save_checkpoint(
        taptr.build_model("tiny"), tmp_path / "cal.pth", visibility_threshold=0.3
    )
    assert cli_main(["convert", str(source), str(tmp_path / "out.pth"), "--half"]) == 0
    assert read_visibility_threshold(tmp_path / "out.pth") == 0.3
