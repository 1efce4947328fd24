"""The training loop on tiny synthetic data: learning, exact resume, divergence, outputs."""

from __future__ import annotations

import itertools
import json
import logging

import pytest
import torch

import taptr
from taptr.cli.main import main as cli_main
from taptr.data.synthetic import SyntheticConfig, write_dataset
from taptr.train import data_parallel, loop
from taptr.train.config import load_config
from taptr.train.dataset import training_sequences
from taptr.train.forward import TrainingForward
from taptr.train.losses import LossOutput, LossWeights
from taptr.train.run_state import load_training_checkpoint


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("synthetic")
    config = SyntheticConfig(height=64, width=64, num_frames=12, num_points=200)
    write_dataset(root / "train", 4, config)
    write_dataset(root / "val", 2, config, seed=1)
    return root


def _config(data, out, *overrides):
    return load_config(
        None,
        [
            "preset=small",
            "model.preset=tiny",
            f"data.root={data / 'train'}",
            "data.val_root=",
            "data.frame_size=[64,64]",
            "data.num_points=24",
            "data.num_workers=0",
            f"out_dir={out}",
            "log_every=1",
            *overrides,
        ],
    )


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Small ops on a shared 2-core machine: a second thread only adds waiting."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_a_few_steps_lower_the_loss(data, tmp_path):
    config = _config(data, tmp_path, "lr=1e-3", "lr_backbone=1e-3")
    info = data_parallel.setup("cpu")
    run = loop._build(config, info, None)
    batches = itertools.repeat(next(loop._batches(config, info, 0)))  # one synthetic clip
    net, weights = TrainingForward(run.model), LossWeights()
    losses = [loop._optimizer_step(net, run, batches, weights, config, info) for _ in range(12)]
    assert losses[-1]["loss"] < 0.75 * losses[0]["loss"]
    assert all(s["grad_norm"] > 0 for s in losses)


def _states(run_dir):
    state = load_training_checkpoint(run_dir / "checkpoint.pt")
    return state["model"], state["ema"], state["optimizer"]["state"]


def test_resume_equals_an_uninterrupted_run(data, tmp_path):
    # window dropout stays on: the resumed run must also restore the random state
    loop.train(_config(data, tmp_path / "full", "steps=4", "checkpoint_every=2"))
    loop.train(_config(data, tmp_path / "split", "steps=2", "checkpoint_every=2"))
    assert load_training_checkpoint(tmp_path / "split" / "checkpoint.pt")["step"] == 2
    # the command line continues it (with a data-loading process this time)
    checkpoint = str(tmp_path / "split" / "checkpoint.pt")
    assert cli_main(["train", "--resume", checkpoint, "steps=4", "data.num_workers=1"]) == 0
    full, split = _states(tmp_path / "full"), _states(tmp_path / "split")
    for ours, theirs in zip(full[:2], split[:2], strict=True):
        assert ours.keys() == theirs.keys()
        assert all(torch.equal(ours[k], theirs[k]) for k in ours)
    for index, values in full[2].items():
        assert all(torch.equal(v, split[2][index][k]) for k, v in values.items())


def test_resume_refuses_a_different_recipe(data, tmp_path):
    loop.train(_config(data, tmp_path, "steps=1"))
    with pytest.raises(ValueError, match=r"config differs in lr \(0.0005 → 0.001\)"):
        loop.train(_config(data, tmp_path, "steps=2", "lr=1e-3"), resume=tmp_path / "checkpoint.pt")


def test_non_finite_loss_stops_and_keeps_the_last_checkpoint(data, tmp_path, monkeypatch):
    calls = {"n": 0}
    real = loop.tracking_loss

    def diverging(*args, **kwargs):
        out = real(*args, **kwargs)
        calls["n"] += 1
        return LossOutput(out.total * float("nan"), out.terms) if calls["n"] == 3 else out

    monkeypatch.setattr(loop, "tracking_loss", diverging)
    config = _config(data, tmp_path, "steps=5", "checkpoint_every=2")
    with pytest.raises(loop.NonFiniteLossError, match=r"step 3: non-finite loss nan.*checkpoint"):
        loop.train(config)
    assert load_training_checkpoint(tmp_path / "checkpoint.pt")["step"] == 2
    assert not (tmp_path / "model.pt").exists()
    monkeypatch.setattr(loop, "tracking_loss", real)
    calls["n"] = 0
    assert cli_main(["train", "--resume", str(tmp_path / "checkpoint.pt")]) == 0


def test_outputs_load_for_inference_with_ema_weights(data, tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="taptr.train")
    config = _config(
        data, tmp_path, "steps=2", f"data.val_root={data / 'val'}", "eval_every=2", "ema_decay=0.5"
    )
    final = loop.train(config)
    assert "eval step 2" in caplog.text and "position error" in caplog.text
    assert "tensorboard is not installed" in caplog.text or (tmp_path / "tensorboard").is_dir()
    saved = json.loads((tmp_path / "config.json").read_text())
    assert load_config(tmp_path / "config.json") == config and saved["steps"] == 2

    state = load_training_checkpoint(tmp_path / "checkpoint.pt")
    from_training = taptr.load_checkpoint(tmp_path / "checkpoint.pt")
    for name, value in from_training.state_dict().items():
        assert torch.equal(value, state["ema"][name])
    assert any(not torch.equal(state["ema"][k], state["model"][k]) for k in state["model"])
    inference = taptr.load_checkpoint(final)
    assert all(torch.equal(v, state["ema"][k]) for k, v in inference.state_dict().items())


def test_evaluation_metrics(data):
    from taptr import build_model
    from taptr.train.dataset import held_out_clips
    from taptr.train.losses import LossWeights
    from taptr.train.validate import evaluate

    config = _config(data, data / "unused")
    sequences = sorted((data / "val").iterdir())
    clips = list(held_out_clips(sequences, config.data, (64, 64), seed=0))
    again = list(held_out_clips(sequences, config.data, (64, 64), seed=0))
    assert all(
        torch.equal(torch.from_numpy(a.tracks), torch.from_numpy(b.tracks))
        for a, b in zip(clips, again, strict=True)
    )
    model = build_model(config.model).train()
    metrics = evaluate(model, clips, LossWeights(), torch.device("cpu"))
    assert model.training  # restored
    for name in ("average_jaccard", "average_pts_within_thresh", "occlusion_accuracy"):
        assert 0 <= metrics[name] <= 1
    assert metrics["position_error"] > 0 and metrics["loss"] > 0 and "position_4" in metrics


def test_bf16_autocast_step_matches_fp32(data, tmp_path):
    info = data_parallel.setup("cpu")
    losses = {}
    for precision in ("fp32", "bf16"):
        config = _config(data, tmp_path, f"precision={precision}", "model.window_dropout=0.0")
        run = loop._build(config, info, None)
        batch = itertools.repeat(next(loop._batches(config, info, 0)))
        step = loop._optimizer_step(
            TrainingForward(run.model), run, batch, LossWeights(), config, info
        )
        losses[precision] = step["loss"]
    assert losses["bf16"] == pytest.approx(losses["fp32"], rel=0.05)


def test_resumed_schedule_follows_the_configured_milestones():
    from taptr.train.optim import apply_milestones, build_optimizer

    def schedule(milestones):
        model = torch.nn.Linear(2, 2)
        return build_optimizer(
            model, lr=1.0, lr_backbone=1.0, weight_decay=0.0, milestones=milestones, gamma=0.1
        )

    optimizer, old = schedule((100,))
    for _ in range(5):
        optimizer.step()
        old.step()
    for milestones, expected in [((3,), 0.1), ((2, 4), 0.01), ((6,), 1.0)]:
        optimizer, resumed = schedule(milestones)
        resumed.load_state_dict(old.state_dict())
        assert resumed.milestones == {100: 1}  # what a plain restore keeps
        apply_milestones(resumed, milestones)
        assert optimizer.param_groups[0]["lr"] == pytest.approx(expected)
        optimizer.step()
        resumed.step()  # step 6: a milestone at 6 drops the rate now
        after = expected * (0.1 if 6 in milestones else 1.0)
        assert optimizer.param_groups[0]["lr"] == pytest.approx(after)


def test_extra_roots_mix_folders_into_one_clip_list(data, tmp_path):
    config = _config(data, tmp_path, "data.extra_roots=" + json.dumps([str(data / "val")]))
    assert config.data.extra_roots == (str(data / "val"),)
    sequences = training_sequences(config.data)
    assert [p.parent.name for p in sequences] == ["train"] * 4 + ["val"] * 2
    missing = _config(data, tmp_path, "data.extra_roots=" + json.dumps([str(tmp_path / "nope")]))
    with pytest.raises(FileNotFoundError, match="nope"):
        training_sequences(missing.data)
    with pytest.raises(ValueError, match=r"data\.root is empty"):
        training_sequences(_config(data, tmp_path, "data.root=").data)


def test_a_v3_model_learns_with_its_recipe(data, tmp_path):
    """TAPTRv3 trains through the per-frame driver; the long-temporal attention, the
    context-aware similarity and the positions of visible entries only all get gradients."""
    config = _config(
        data,
        tmp_path,
        "model.preset=tiny-v3",
        "model.input_size=[64,64]",
        "supervise_occluded_positions=false",
        "lr=1e-3",
        "lr_backbone=1e-3",
    )
    info = data_parallel.setup("cpu")
    run = loop._build(config, info, None)
    batches = itertools.repeat(next(loop._batches(config, info, 0)))
    weights = LossWeights(occluded_positions=False)
    net = TrainingForward(run.model)
    layer = run.model.decoder.layers[0]
    watched = {
        "long-temporal": layer.long_temporal.attention.in_proj_weight,
        "similarity": layer.cross_attention.similarity.layers[0].weight,
        "rotary": layer.long_temporal.rotary.freqs,
    }
    before = {name: param.detach().clone() for name, param in watched.items()}
    losses = [loop._optimizer_step(net, run, batches, weights, config, info) for _ in range(8)]
    assert losses[-1]["loss"] < 0.8 * losses[0]["loss"]
    assert not torch.equal(watched["long-temporal"], before["long-temporal"])
    assert not torch.equal(watched["similarity"], before["similarity"])
    assert torch.equal(watched["rotary"], before["rotary"])  # a fixed table


def test_a_run_that_fails_before_its_first_checkpoint_leaves_nothing(data, tmp_path, capsys):
    empty = tmp_path / "empty"  # exists, holds no sequence: found only once the run started
    empty.mkdir()
    base = ["train", "preset=small", "model.preset=tiny", f"data.root={empty}", "data.val_root="]
    assert cli_main([*base, f"out_dir={tmp_path / 'new'}"]) == 2
    assert "no sequence" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()  # config.json and the folder itself are gone
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "notes.txt").write_text("mine")
    assert cli_main([*base, f"out_dir={tmp_path / 'old'}"]) == 2
    assert [p.name for p in (tmp_path / "old").iterdir()] == ["notes.txt"]


def test_a_failed_run_with_a_checkpoint_is_kept_and_says_so(data, tmp_path, monkeypatch, capsys):
    def diverging(*args, **kwargs):
        raise KeyboardInterrupt  # Ctrl-C after the first checkpoint

    out = tmp_path / "run"
    argv = [
        "train",
        "preset=small",
        "model.preset=tiny",
        f"data.root={data / 'train'}",
        "data.val_root=",
        "data.frame_size=[64,64]",
        "data.num_points=24",
        "data.num_workers=0",
        "steps=3",
        "checkpoint_every=1",
        f"out_dir={out}",
    ]
    real = loop._optimizer_step
    calls = {"n": 0}

    def interrupted(*args, **kwargs):
        calls["n"] += 1
        return diverging() if calls["n"] == 2 else real(*args, **kwargs)

    monkeypatch.setattr(loop, "_optimizer_step", interrupted)
    assert cli_main(argv) == 130
    assert (out / "checkpoint.pt").is_file() and (out / "config.json").is_file()
    assert f"kept {out}: 'taptr train --resume --out {out}' continues" in capsys.readouterr().err
