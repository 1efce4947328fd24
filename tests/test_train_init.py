"""Starting weights (ImageNet backbone, --init-from) and the command line's error paths."""

from __future__ import annotations

import logging

import pytest
import torch
from torchvision.models import resnet50

import taptr
from taptr.cli.main import main as cli_main
from taptr.official.convert import convert_state_dict
from taptr.train import data_parallel, loop
from taptr.train.config import load_config
from taptr.train.initialise import RESNET50_IMAGENET_FILE, init_backbone, init_from_checkpoint
from taptr.weights.checkpoint import CheckpointError


@pytest.fixture(scope="module")
def imagenet_file(tmp_path_factory):
    """A file laid out like torchvision's ResNet-50 weights (random values)."""
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("hub") / RESNET50_IMAGENET_FILE
    torch.save(resnet50(weights=None).state_dict(), path)
    return path


@pytest.fixture(scope="module")
def paper_model():
    return taptr.build_model("taptrv2")


def test_backbone_from_torchvision_weights(imagenet_file, paper_model):
    assert init_backbone(paper_model, str(imagenet_file))
    reference = torch.load(imagenet_file, weights_only=True)
    body = paper_model.backbone.body.state_dict()
    assert all(torch.equal(body[k], reference[k]) for k in body)


def test_auto_uses_the_torchvision_cache_or_trains_from_scratch(
    imagenet_file, paper_model, tmp_path, monkeypatch, caplog
):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    with caplog.at_level(logging.WARNING, logger="taptr.train"):
        assert not init_backbone(paper_model, "auto")
    assert "from scratch" in caplog.text
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / RESNET50_IMAGENET_FILE).symlink_to(imagenet_file)
    assert init_backbone(paper_model, "auto")
    assert not init_backbone(paper_model, "none")


def test_light_backbone_has_no_imagenet_weights(imagenet_file):
    model = taptr.build_model("tiny")
    assert not init_backbone(model, "auto")
    with pytest.raises(ValueError, match="backbone is 'convnet'"):
        init_backbone(model, str(imagenet_file))
    with pytest.raises(FileNotFoundError):
        init_backbone(taptr.build_model("taptrv2"), "/nonexistent/resnet50.pth")


def test_init_from_the_authors_release(official_checkpoint, official_state_dict, paper_model):
    init_from_checkpoint(paper_model, str(official_checkpoint))
    expected, _ = convert_state_dict(official_state_dict)
    ours = paper_model.state_dict()
    assert all(torch.equal(ours[k], expected[k]) for k in expected)


def test_a_run_starts_from_init_from(tmp_path):
    torch.manual_seed(5)
    source = taptr.build_model("tiny")
    taptr.save_checkpoint(source, tmp_path / "start.pt")
    config = load_config(
        None, ["preset=small", "model.preset=tiny", f"init_from={tmp_path / 'start.pt'}"]
    )
    run = loop._build(config, data_parallel.setup("cpu"), None)
    for name, value in source.state_dict().items():
        assert torch.equal(run.model.state_dict()[name], value)
        assert torch.equal(run.ema.state_dict()[name], value)


def test_init_from_a_mismatched_checkpoint_lists_the_keys(tmp_path):
    taptr.save_checkpoint(taptr.build_model("tiny"), tmp_path / "tiny.pt")
    config = load_config(None, ["preset=small", f"init_from={tmp_path / 'tiny.pt'}"])
    with pytest.raises(CheckpointError, match="wrong shape"):
        loop._build(config, data_parallel.setup("cpu"), None)


def test_train_command_errors_are_one_line(tmp_path, capsys):
    assert cli_main(["train", "preset=small", f"data.root={tmp_path / 'none'}"]) == 2
    assert f"data.root {tmp_path / 'none'}: dataset folder not found" in capsys.readouterr().err
    assert cli_main(["train", "--out", str(tmp_path), "--resume"]) == 2
    assert "no checkpoint to resume from" in capsys.readouterr().err
    assert cli_main(["train", "--config", str(tmp_path / "x.toml")]) == 2
    assert cli_main(["train", "stepz=1"]) == 2
    assert "unknown config keys: stepz" in capsys.readouterr().err
    missing = tmp_path / "release.pth"
    assert cli_main(["train", "preset=small", "--init-from", str(missing)]) == 2
    assert f"checkpoint not found: {missing}" in capsys.readouterr().err


def test_init_from_builds_no_second_model(tmp_path, monkeypatch):
    import taptr.weights.checkpoint as checkpoint_module

    torch.manual_seed(6)
    source = taptr.build_model("tiny")
    taptr.save_checkpoint(source, tmp_path / "start.pt")
    target = taptr.build_model("tiny")
    built = []
    real_build = checkpoint_module.build_model

    def counting_build(config):
        built.append(torch.empty(()).device.type)  # "meta" inside the shape check
        return real_build(config)

    monkeypatch.setattr(checkpoint_module, "build_model", counting_build)
    checkpoint_module._skeleton.cache_clear()
    init_from_checkpoint(target, str(tmp_path / "start.pt"))
    assert "cpu" not in built  # only the meta-device skeleton of the shape check
    assert all(torch.equal(target.state_dict()[k], v) for k, v in source.state_dict().items())


def test_init_parts_copy_only_those_parts(tmp_path):
    torch.manual_seed(7)
    source = taptr.build_model("tiny")
    taptr.save_checkpoint(source, tmp_path / "start.pt")
    torch.manual_seed(8)
    config = load_config(
        None,
        [
            "preset=small",
            "model.preset=tiny",
            "model.position_update=false",
            "model.disentangler=false",
            f"init_from={tmp_path / 'start.pt'}",
            'init_parts=["backbone", "input_projections", "encoder"]',
        ],
    )
    assert not config.model.position_update
    run = loop._build(config, data_parallel.setup("cpu"), None)
    theirs, ours = source.state_dict(), run.model.state_dict()
    copied = [k for k in ours if k.split(".")[0] in config.init_parts]
    assert copied and all(torch.equal(ours[k], theirs[k]) for k in copied)
    fresh = [k for k in ours if k.startswith("decoder.") and k.endswith("value_proj.weight")]
    assert fresh and not any(torch.equal(ours[k], theirs[k]) for k in fresh)


def test_init_parts_are_checked():
    with pytest.raises(ValueError, match="unknown init_parts"):
        load_config(None, ["init_from=x.pt", 'init_parts=["encodr"]'])
    with pytest.raises(ValueError, match="init_parts needs init_from"):
        load_config(None, ['init_parts=["encoder"]'])
