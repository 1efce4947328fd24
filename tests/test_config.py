"""Configs: presets, validation and plain-data round trips."""

from __future__ import annotations

import json

import pytest

from taptr.config import BackboneConfig, ModelConfig, get_config, taptrv2, tiny


def test_paper_defaults():
    config = taptrv2()
    assert (config.d_model, config.num_heads, config.encoder_layers, config.decoder_layers) == (
        256,
        8,
        2,
        5,
    )
    assert (config.window_size, config.window_stride, config.sine_temperature) == (8, 4, 10.0)
    assert config.cross_attention == "key_aware" and config.position_update and config.disentangler
    assert config.num_levels == 4 and config.input_size == (512, 512)
    assert config == ModelConfig()


@pytest.mark.parametrize("preset", ["taptrv2", "tiny"])
def test_round_trip_through_json(preset):
    config = get_config(preset)
    data = json.loads(json.dumps(config.to_dict()))
    assert ModelConfig.from_dict(data) == config


def test_unknown_preset_lists_known_ones():
    with pytest.raises(KeyError, match="taptrv2"):
        get_config("taptr-v9")


def test_unknown_keys_are_named():
    data = tiny().to_dict()
    data["decoder_depth"] = 3
    with pytest.raises(ValueError, match="decoder_depth"):
        ModelConfig.from_dict(data)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        (dict(d_model=30), "divisible"),
        (dict(cross_attention="dense"), "cross_attention"),
        (dict(position_update=False), "disentangler"),
        (dict(window_stride=9), "window_stride"),
        (dict(decoder_layers=0), "decoder layer"),
    ],
)
def test_invalid_configs(changes, message):
    with pytest.raises(ValueError, match=message):
        tiny().replace(**changes)


def test_backbone_validation():
    with pytest.raises(ValueError, match="fixed widths"):
        BackboneConfig(kind="resnet50", channels=(1, 2, 3, 4))
    with pytest.raises(ValueError, match="unknown backbone"):
        BackboneConfig(kind="vit")  # type: ignore[arg-type]


def test_replace_accepts_backbone_dict():
    config = tiny().replace(backbone={"kind": "convnet", "channels": [8, 8, 8, 8]})
    assert config.backbone == BackboneConfig("convnet", (8, 8, 8, 8))
