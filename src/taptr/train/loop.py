"""The training loop: step-based, data-parallel, with accumulation, EMA and checkpoints.

One optimizer step runs ``grad_accum`` micro-batches (gradients are all-reduced on the last
one only), clips the global gradient norm, steps AdamW and the schedule, and moves the EMA.
Rank 0 logs the means of every ``log_every`` steps, evaluates the EMA model on held-out clips every
``eval_every`` steps and writes ``checkpoint.pt`` every ``checkpoint_every`` steps; the end
of the run writes ``model.pt``, the EMA weights alone, for inference. A non-finite loss
stops every process before its gradients are used, leaving the last checkpoint as it was.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn, optim

from taptr.data.kubric import list_sequences
from taptr.data.sampling import ClipBatch
from taptr.io.atomic import atomic_path
from taptr.model.build import build_model
from taptr.model.taptr import TAPTR
from taptr.process_group import gather_objects
from taptr.train import data_parallel
from taptr.train.config import TrainConfig
from taptr.train.dataset import (
    ClipDataset,
    MicroBatchSampler,
    clip_loader,
    held_out_clips,
    training_sequences,
)
from taptr.train.ema import ModelEMA
from taptr.train.forward import TrainingForward, batch_targets
from taptr.train.initialise import init_backbone, init_from_checkpoint
from taptr.train.losses import LossWeights, tracking_loss
from taptr.train.monitor import Monitor
from taptr.train.optim import apply_milestones, build_optimizer
from taptr.train.precision import autocast, grad_scaler
from taptr.train.run_state import (
    CHECKPOINT_NAME,
    check_resumable,
    load_training_checkpoint,
    restore,
    rng_state,
    save_training_checkpoint,
)
from taptr.train.validate import evaluate
from taptr.weights.checkpoint import save_checkpoint

logger = logging.getLogger(__name__)

MODEL_NAME = "model.pt"


class NonFiniteLossError(FloatingPointError):
    """The loss (or the gradient norm) became NaN or infinite; the run stopped."""


@dataclass
class Run:
    """The objects a run updates."""

    model: TAPTR
    ema: ModelEMA[TAPTR]
    optimizer: optim.AdamW
    scheduler: optim.lr_scheduler.MultiStepLR
    scaler: torch.amp.GradScaler
    step: int


def _build(
    config: TrainConfig, info: data_parallel.Distributed, resume: str | os.PathLike[str] | None
) -> Run:
    """Fresh (or initialised, or resumed) model, EMA, optimiser, schedule and scaler."""
    state = None
    if resume is not None:
        state = load_training_checkpoint(resume)
        check_resumable(config, state["train_config"], str(resume))
    data_parallel.seed_process(config.seed, 0)  # the same fresh weights on every process
    # the grid_sample kernel: its backward is about half the gather kernel's cost on CPU
    # (see taptr.model.execution)
    model = build_model(config.model, execution="training")
    if state is None:
        init_backbone(model, config.backbone_weights)
        if config.init_from:
            init_from_checkpoint(model, config.init_from, config.init_parts)
    model.to(info.device).train()
    optimizer, scheduler = build_optimizer(
        model,
        lr=config.lr,
        lr_backbone=config.lr_backbone,
        weight_decay=config.weight_decay,
        milestones=config.lr_milestones,
        gamma=config.lr_gamma,
    )
    run = Run(
        model,
        ModelEMA(model, config.ema_decay),
        optimizer,
        scheduler,
        grad_scaler(config.precision, info.device),
        0,
    )
    data_parallel.seed_process(config.seed, info.rank)  # dropout masks differ per process
    if state is not None:
        run.step = restore(
            state,
            model=model,
            ema=run.ema,
            optimizer=optimizer,
            scheduler=scheduler,
            scaler=run.scaler,
            rank=info.rank,
            world_size=info.world_size,
        )
        apply_milestones(scheduler, config.lr_milestones)
        logger.info("resumed from %s after step %d", resume, run.step)
    return run


def _batches(
    config: TrainConfig, info: data_parallel.Distributed, step: int
) -> Iterator[ClipBatch]:
    """This process's micro-batches from optimizer step ``step`` on."""
    dataset = ClipDataset(
        training_sequences(config.data), config.data, config.model.input_size, config.seed
    )
    sampler = MicroBatchSampler(
        step * config.grad_accum,
        config.steps * config.grad_accum,
        info.rank,
        info.world_size,
        config.batch_size,
    )
    return iter(clip_loader(dataset, sampler, config.data.num_workers))


def _optimizer_step(
    net: nn.Module,
    run: Run,
    batches: Iterator[ClipBatch],
    weights: LossWeights,
    config: TrainConfig,
    info: data_parallel.Distributed,
) -> dict[str, float]:
    """Accumulates ``grad_accum`` micro-batches, clips and steps; returns mean loss terms."""
    sums: dict[str, float] = defaultdict(float)
    waited = 0.0
    for micro in range(config.grad_accum):
        tic = time.perf_counter()
        batch = next(batches).to(info.device)
        waited += time.perf_counter() - tic
        with data_parallel.no_sync(net, skip=micro < config.grad_accum - 1):
            with autocast(config.precision, info.device):
                output = net(*batch)
            loss = tracking_loss(output, batch_targets(batch), weights)
            if not data_parallel.all_finite(loss.total):
                terms = ", ".join(f"{k} {v.item():.4g}" for k, v in loss.terms.items())
                raise NonFiniteLossError(f"non-finite loss {loss.total.item()} ({terms})")
            run.scaler.scale(loss.total / config.grad_accum).backward()
        sums["loss"] += loss.total.item() / config.grad_accum
        for name, value in loss.terms.items():
            sums[name] += value.item() / config.grad_accum
    run.scaler.unscale_(run.optimizer)
    norm = nn.utils.clip_grad_norm_(run.model.parameters(), config.clip_norm or math.inf)
    if not run.scaler.is_enabled() and not torch.isfinite(norm):
        raise NonFiniteLossError(f"non-finite gradient norm {norm.item()}")
    run.scaler.step(run.optimizer)  # skipped by the fp16 scaler after an overflow
    run.scaler.update()
    run.optimizer.zero_grad(set_to_none=True)
    return {**sums, "grad_norm": norm.item(), "data_seconds": waited}


def _save(run: Run, config: TrainConfig, info: data_parallel.Distributed, path: Path) -> None:
    states = gather_objects(rng_state())  # every process's dropout generator
    if info.is_main:
        save_training_checkpoint(
            path,
            model=run.model,
            ema=run.ema,
            optimizer=run.optimizer,
            scheduler=run.scheduler,
            scaler=run.scaler,
            step=run.step,
            config=config,
            rng=states,
        )


def _periodic(
    run: Run,
    config: TrainConfig,
    info: data_parallel.Distributed,
    monitor: Monitor,
    held_out: list[Path],
    weights: LossWeights,
) -> bool:
    """Logs, evaluates and saves when their step comes; returns whether it saved."""
    last = run.step == config.steps
    if run.step % config.log_every == 0 or last:
        means = data_parallel.mean_over_processes(monitor.means(), info.device)
        monitor.train(run.step, {**means, "lr": run.optimizer.param_groups[-1]["lr"]})
    if held_out and (run.step % config.eval_every == 0 or last):
        if info.is_main:  # the others wait at the barrier
            clips = held_out_clips(held_out, config.data, config.model.input_size, config.seed)
            metrics = evaluate(run.ema.module, clips, weights, info.device, config.precision)
            monitor.evaluation(run.step, metrics)
        data_parallel.barrier()
    if run.step % config.checkpoint_every == 0 or last:
        _save(run, config, info, Path(config.out_dir) / CHECKPOINT_NAME)
        return True
    return False


def train(config: TrainConfig, resume: str | os.PathLike[str] | None = None) -> Path:
    """Trains (or resumes) a run; works alone and under ``torchrun``.

    Args:
        config: the resolved configuration (saved as ``<out_dir>/config.json``).
        resume: a training checkpoint to continue from (its config must match).

    Returns:
        ``<out_dir>/model.pt``, the final EMA weights for inference.

    Raises:
        NonFiniteLossError: the loss diverged; the message names the last good checkpoint.
    """
    info = data_parallel.setup(config.device)
    try:
        run_dir = Path(config.out_dir)
        run = _build(config, info, resume)
        if info.is_main:
            with atomic_path(run_dir / "config.json") as tmp:
                tmp.write_text(json.dumps(config.to_dict(), indent=2) + "\n")
        net = data_parallel.wrap(TrainingForward(run.model), info)
        batches = _batches(config, info, run.step)
        held_out = []
        if config.data.val_root and config.eval_every:
            held_out = list_sequences(config.data.val_root)[: config.data.val_videos]
        weights = LossWeights(
            config.visibility_weight,
            config.position_weight,
            config.supervise_updated_positions,
            # TAPTR v1 normalises its terms by the plain counts
            count_offset=1.0 if run.model.config is None or run.model.config.version != 1 else 0.0,
            occluded_positions=config.supervise_occluded_positions,
        )
        monitor = Monitor(run_dir / "tensorboard", info.is_main, config.steps, run.step)
        saved = Path(resume) if resume is not None else None
        while run.step < config.steps:
            try:
                scalars = _optimizer_step(net, run, batches, weights, config, info)
            except NonFiniteLossError as error:
                kept = f"the last good checkpoint is {saved}" if saved else "no checkpoint yet"
                raise NonFiniteLossError(f"step {run.step + 1}: {error}; stopped, {kept}") from None
            run.scheduler.step()
            run.ema.update(run.model, steps=config.grad_accum)
            run.step += 1
            monitor.add(scalars)
            if _periodic(run, config, info, monitor, held_out, weights):
                saved = run_dir / CHECKPOINT_NAME
        monitor.close()
        final = run_dir / MODEL_NAME
        if info.is_main:
            save_checkpoint(run.ema.module, final)
        return final
    finally:
        data_parallel.teardown()
