"""Training configuration: presets, files, overrides, optimiser groups, EMA math, precision."""

from __future__ import annotations

import json

import pytest
import torch

from taptr.config import get_config
from taptr.train.config import (
    DataConfig,
    TrainConfig,
    from_dict,
    load_config,
    parse_overrides,
)
from taptr.train.ema import ModelEMA
from taptr.train.optim import build_optimizer
from taptr.train.precision import autocast, grad_scaler


def test_default_is_the_official_recipe():
    config = TrainConfig()
    assert config.model == get_config("taptrv2")
    assert (config.lr, config.lr_backbone, config.weight_decay) == (2e-4, 1e-5, 1e-4)
    assert (config.clip_norm, config.grad_accum, config.ema_decay) == (0.1, 4, 0.9997)
    assert config.data.num_points == 800 and not config.data.bgr
    assert config.lr_milestones[0] / config.steps == pytest.approx(100 / 150, abs=1e-3)


def test_small_preset_uses_the_small_model():
    config = from_dict({"preset": "small"})
    assert config.model == get_config("small")
    assert config.model.backbone.kind == "convnet"
    assert config.data.frame_size == config.model.input_size


def test_file_then_overrides(tmp_path):
    toml = tmp_path / "run.toml"
    toml.write_text(
        'preset = "small"\nsteps = 30\n[model]\npreset = "tiny"\nd_model = 48\n'
        '[model.backbone]\nchannels = [8, 8, 16, 16]\n[data]\nroot = "x"\n'
    )
    config = load_config(toml, ["steps=7", "data.frame_size=[32,48]", "lr=0.001"])
    assert config.steps == 7 and config.lr == 1e-3
    assert config.model.d_model == 48 and config.model.num_heads == get_config("tiny").num_heads
    assert config.model.backbone.channels == (8, 8, 16, 16)
    assert config.data.root == "x" and config.data.frame_size == (32, 48)
    # the resolved config a run writes is itself a config file
    saved = tmp_path / "config.json"
    saved.write_text(json.dumps(config.to_dict()))
    assert load_config(saved) == config


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["stepz=3"], "unknown config keys: stepz"),
        (["data.rooot=x"], "data.rooot"),
        (["model.backbone.kind=vit"], "unknown backbone kind"),
        (["steps=ten"], "'steps' must be of type int"),
        (["data.camera_panning=1"], "must be of type bool"),
        (["preset=huge"], "unknown training preset"),
        (["precision=fp8"], "precision must be"),
        (["steps"], "not KEY=VALUE"),
    ],
)
def test_bad_settings_are_named(overrides, message):
    with pytest.raises(ValueError, match=message):
        load_config(None, overrides)


def test_override_values_parse_as_json_or_text():
    assert parse_overrides(["a.b=1", "a.c=[1, 2]", "d=true", "e=runs/x"]) == {
        "a": {"b": 1, "c": [1, 2]},
        "d": True,
        "e": "runs/x",
    }


def test_missing_config_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_config(tmp_path / "nope.toml")
    (tmp_path / "a.yaml").write_text("x: 1")
    with pytest.raises(ValueError, match=r"\.toml or \.json"):
        load_config(tmp_path / "a.yaml")


def test_two_optimiser_groups_and_milestones():
    from taptr import build_model

    model = build_model("tiny")
    optimizer, scheduler = build_optimizer(
        model, lr=2e-4, lr_backbone=1e-5, weight_decay=1e-4, milestones=(2, 3), gamma=0.1
    )
    backbone, rest = optimizer.param_groups
    assert backbone["lr"] == 1e-5 and rest["lr"] == 2e-4
    assert backbone["weight_decay"] == rest["weight_decay"] == 1e-4
    names = {id(p): n for n, p in model.named_parameters()}
    assert all(names[id(p)].startswith("backbone.") for p in backbone["params"])
    assert len(backbone["params"]) + len(rest["params"]) == len(list(model.parameters()))
    lrs = []
    for _ in range(4):
        optimizer.step()
        scheduler.step()
        lrs.append(optimizer.param_groups[1]["lr"])
    assert lrs == pytest.approx([2e-4, 2e-5, 2e-6, 2e-6])


def test_ema_update_math():
    model = torch.nn.Linear(2, 1)
    torch.nn.init.constant_(model.weight, 1.0)
    ema = ModelEMA(model, decay=0.9)
    torch.nn.init.constant_(model.weight, 3.0)
    ema.update(model)
    assert ema.module.weight[0, 0].item() == pytest.approx(0.9 * 1 + 0.1 * 3)
    # k micro-batch updates with unchanged weights = one update with decay ** k
    twice = ModelEMA(model, decay=0.9)
    torch.nn.init.constant_(twice.module.weight, 1.0)
    twice.update(model, steps=2)
    ema_by_hand = 0.9 * (0.9 * 1 + 0.1 * 3) + 0.1 * 3
    assert twice.module.weight[0, 0].item() == pytest.approx(ema_by_hand)
    assert not any(p.requires_grad for p in ema.module.parameters())


def test_ema_copies_integer_buffers():
    model = torch.nn.BatchNorm1d(2)
    ema = ModelEMA(model, decay=0.5)
    model.num_batches_tracked += 7
    ema.update(model)
    assert ema.module.num_batches_tracked.item() == 7


def test_precision_settings():
    cpu = torch.device("cpu")
    with autocast("bf16", cpu):
        assert torch.get_autocast_dtype("cpu") == torch.bfloat16 and torch.is_autocast_enabled(
            "cpu"
        )
    with autocast("fp32", cpu):
        assert not torch.is_autocast_enabled("cpu")
    assert not grad_scaler("bf16", cpu).is_enabled()
    with pytest.raises(ValueError, match="fp16 needs a CUDA"):
        grad_scaler("fp16", cpu)


def test_data_config_defaults_are_the_official_augmentation():
    data = DataConfig()
    assert (data.eraser_prob, data.replace_prob, data.colour_prob, data.blur_prob) == (
        0.5,
        0.5,
        0.25,
        0.25,
    )
    assert (data.hflip_prob, data.vflip_prob, data.restart_fraction) == (0.5, 0.5, 0.25)


def test_shipped_config_files_load():
    from pathlib import Path

    configs = Path(__file__).parents[1] / "configs"
    assert load_config(configs / "small.toml") == from_dict({"preset": "small"})
    paper = load_config(configs / "taptrv2_kubric.toml")
    assert paper.model == get_config("taptrv2") and paper.data.num_points == 800
    stage2 = load_config(configs / "small_photo.toml")
    assert stage2.model == load_config(configs / "small.toml").model
    assert stage2.data.extra_roots == ("data/synthetic_photo/train",)
    assert stage2.init_from == load_config(configs / "ablation_apu.toml").init_from
    # stage 3 continues from stage 2's output, on the same data, with the same model
    stage3 = load_config(configs / "small_photo_stage3.toml")
    assert stage3.init_from == f"{stage2.out_dir}/model.pt"
    assert (stage3.model, stage3.data) == (stage2.model, stage2.data)
