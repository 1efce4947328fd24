"""The optimiser recipe (spec §5.4): two AdamW groups and a step-wise MultiStepLR.

Parameters whose name contains ``backbone`` form one group (official: lr 1e-5), all others
the second (2e-4); both use weight decay 1e-4. The official configuration has no extra
multiplier for the sampling offsets (spec §1.2). The learning rates drop by ``gamma`` after
each milestone, counted in optimizer steps (the official code counts epochs).
"""

from __future__ import annotations

from collections import Counter

from torch import nn, optim


def parameter_groups(model: nn.Module, lr: float, lr_backbone: float) -> list[dict]:
    """The backbone group first, then everything else (trainable parameters only)."""
    backbone: list[nn.Parameter] = []
    rest: list[nn.Parameter] = []
    for name, param in model.named_parameters():
        if param.requires_grad:
            (backbone if "backbone" in name else rest).append(param)
    groups = [{"params": backbone, "lr": lr_backbone, "name": "backbone"}]
    return [g for g in groups if g["params"]] + [{"params": rest, "lr": lr, "name": "rest"}]


def build_optimizer(
    model: nn.Module,
    *,
    lr: float,
    lr_backbone: float,
    weight_decay: float,
    milestones: tuple[int, ...],
    gamma: float,
) -> tuple[optim.AdamW, optim.lr_scheduler.MultiStepLR]:
    """AdamW over the two groups and its MultiStepLR schedule (step it once per update)."""
    optimizer = optim.AdamW(
        parameter_groups(model, lr, lr_backbone), lr=lr, weight_decay=weight_decay
    )
    scheduler = optim.lr_scheduler.MultiStepLR(optimizer, list(milestones), gamma=gamma)
    return optimizer, scheduler


def apply_milestones(
    scheduler: optim.lr_scheduler.MultiStepLR, milestones: tuple[int, ...]
) -> None:
    """Makes a restored schedule follow ``milestones`` from its current step on.

    A resumed run may change its milestones, but the scheduler's saved state carries the old
    ones, so the configured milestones are set again and the learning rates recomputed for
    the step reached (one drop by ``gamma`` per milestone at or before it).
    """
    scheduler.milestones = Counter(milestones)
    drops = sum(1 for m in milestones if m <= scheduler.last_epoch)
    for group, base in zip(scheduler.optimizer.param_groups, scheduler.base_lrs, strict=True):
        group["lr"] = base * scheduler.gamma**drops
    scheduler._last_lr = [group["lr"] for group in scheduler.optimizer.param_groups]
