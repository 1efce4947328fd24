"""Training checkpoints: the full state of a run, written atomically, resumed exactly.

A training checkpoint is taptr's checkpoint format (`taptr.weights.checkpoint`: ``format``,
``version``, ``config``, ``model``, ``ema``) plus the entries a resumed run needs:
``train_config``, ``optimizer``, ``scheduler``, ``scaler``, ``step`` and ``rng`` (every
process's torch generator states). `taptr.load_checkpoint` therefore loads one directly,
with the EMA weights.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import torch
from torch import optim

from taptr.io.atomic import atomic_path
from taptr.model.taptr import TAPTR
from taptr.train.config import TrainConfig
from taptr.train.ema import ModelEMA
from taptr.weights.checkpoint import CheckpointError, checkpoint_dict, read_file

logger = logging.getLogger(__name__)

CHECKPOINT_NAME = "checkpoint.pt"

# Fields that may differ when resuming: they do not change what the steps compute.
RESUMABLE_CHANGES = frozenset(
    {
        "steps",
        "lr_milestones",
        "log_every",
        "eval_every",
        "checkpoint_every",
        "out_dir",
        "device",
        "init_from",
        "init_parts",
        "backbone_weights",
        "data.num_workers",
        "data.val_root",
        "data.val_videos",
    }
)


def rng_state() -> dict[str, Any]:
    """This process's torch generator states (CPU and every CUDA device)."""
    cuda = torch.cuda.get_rng_state_all() if torch.cuda.is_available() else []
    return {"torch": torch.get_rng_state(), "cuda": cuda}


def set_rng_state(state: dict[str, Any]) -> None:
    """Restores what `rng_state` returned."""
    torch.set_rng_state(state["torch"])
    if state["cuda"] and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_training_checkpoint(
    path: str | os.PathLike[str],
    *,
    model: TAPTR,
    ema: ModelEMA[TAPTR],
    optimizer: optim.Optimizer,
    scheduler: optim.lr_scheduler.LRScheduler,
    scaler: torch.amp.GradScaler,
    step: int,
    config: TrainConfig,
    rng: list[dict[str, Any]],
) -> Path:
    """Writes the run's state after ``step`` optimizer steps, atomically.

    Args:
        path: destination file.
        model: the trained model.
        ema: its moving average (what inference loads).
        optimizer: optimiser.
        scheduler: learning-rate schedule.
        scaler: loss scaler.
        step: optimizer steps done.
        config: the run's resolved config.
        rng: every process's `rng_state`, in rank order.
    """
    data = checkpoint_dict(model, ema.state_dict())
    data.update(
        train_config=config.to_dict(),
        optimizer=optimizer.state_dict(),
        scheduler=scheduler.state_dict(),
        scaler=scaler.state_dict(),
        step=step,
        rng=rng,
    )
    with atomic_path(path) as tmp:
        torch.save(data, tmp)
    return Path(path)


def load_training_checkpoint(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Reads a training checkpoint (safely, ``weights_only``).

    Raises:
        FileNotFoundError: no such file.
        CheckpointError: the file is not a taptr training checkpoint.
    """
    data = read_file(path)
    missing = [k for k in ("train_config", "optimizer", "step", "ema") if k not in data]
    if missing:
        raise CheckpointError(
            f"{path} is not a taptr training checkpoint (missing {', '.join(missing)}); "
            "to start a new run from its weights use init_from"
        )
    return data


def _flatten(data: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat = {}
    for key, value in data.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[prefix + key] = value
    return flat


def check_resumable(config: TrainConfig, saved: dict[str, Any], source: str) -> None:
    """Raises ValueError naming every setting that differs from the checkpoint's run."""
    ours, theirs = _flatten(config.to_dict()), _flatten(saved)
    differ = sorted(
        k
        for k in set(ours) | set(theirs)
        if ours.get(k) != theirs.get(k) and k not in RESUMABLE_CHANGES
    )
    if differ:
        shown = ", ".join(f"{k} ({theirs.get(k)!r} → {ours.get(k)!r})" for k in differ[:8])
        raise ValueError(f"cannot resume from {source}: the config differs in {shown}")


def restore(
    state: dict[str, Any],
    *,
    model: TAPTR,
    ema: ModelEMA[TAPTR],
    optimizer: optim.Optimizer,
    scheduler: optim.lr_scheduler.LRScheduler,
    scaler: torch.amp.GradScaler,
    rank: int,
    world_size: int,
) -> int:
    """Loads a training checkpoint into the run's objects; returns the steps already done."""
    model.load_state_dict(state["model"], strict=True)
    ema.load_state_dict(state["ema"])
    optimizer.load_state_dict(state["optimizer"])
    scheduler.load_state_dict(state["scheduler"])
    scaler.load_state_dict(state["scaler"])
    if len(state["rng"]) == world_size:
        set_rng_state(state["rng"][rank])
    else:
        logger.warning(
            "the checkpoint was written by %d processes, not %d: random states are reseeded, "
            "so dropout masks differ from an uninterrupted run",
            len(state["rng"]),
            world_size,
        )
    return int(state["step"])
