"""Process-group setup for ``torchrun`` data parallelism, and the few collectives we need.

Under ``torchrun`` (``WORLD_SIZE`` > 1) every process joins a group: NCCL when it trains on
CUDA, gloo on CPU. A single process needs no group, and every helper then does the local
thing, so the loop reads the same either way.
"""

from __future__ import annotations

import contextlib
import os
import random
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import nn
from torch.nn.parallel import DistributedDataParallel

from taptr.process_group import join_process_group, launched_world_size


@dataclass(frozen=True)
class Distributed:
    """Where this process sits.

    Attributes:
        rank: global rank (0 logs, evaluates and writes files).
        world_size: number of processes.
        device: this process's device.
    """

    rank: int
    world_size: int
    device: torch.device

    @property
    def is_main(self) -> bool:
        """Whether this is rank 0."""
        return self.rank == 0


def setup(device: str = "auto") -> Distributed:
    """Joins the process group started by ``torchrun`` (if any) and picks the device.

    Args:
        device: ``auto`` (CUDA when available), ``cuda`` or ``cpu``.
    """
    if device not in ("auto", "cuda", "cpu"):
        raise ValueError(f"device must be auto, cuda or cpu, got {device!r}")
    use_cuda = device == "cuda" or (device == "auto" and torch.cuda.is_available())
    if use_cuda and not torch.cuda.is_available():
        raise ValueError("device 'cuda' requested but CUDA is not available")
    world_size = launched_world_size()
    rank = int(os.environ.get("RANK", "0"))
    if use_cuda:
        local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local_rank)
        target = torch.device("cuda", local_rank)
    else:
        target = torch.device("cpu")
    join_process_group(use_cuda)
    return Distributed(rank, world_size, target)


def teardown() -> None:
    """Leaves the process group, if one was joined."""
    if dist.is_initialized():
        dist.destroy_process_group()


def seed_process(seed: int, rank: int) -> None:
    """Seeds torch, numpy's and Python's global generators with ``seed + rank``.

    The data pipeline draws from its own per-clip generators; these seeds decide the
    fresh weights (identical on all ranks when seeded before building the model) and the
    dropout masks.
    """
    random.seed(seed + rank)
    np.random.seed(seed + rank)
    torch.manual_seed(seed + rank)


def wrap(module: nn.Module, info: Distributed) -> nn.Module:
    """The module in DistributedDataParallel when there are several processes.

    Unused parameters are searched for every step: a clip whose windows all get skipped
    (or a single-window clip) leaves some modules without a gradient.
    """
    if info.world_size == 1:
        return module
    device_ids = [info.device.index] if info.device.type == "cuda" else None
    return DistributedDataParallel(module, device_ids=device_ids, find_unused_parameters=True)


def no_sync(module: nn.Module, skip: bool) -> contextlib.AbstractContextManager[Any]:
    """Skips the gradient all-reduce of this backward (micro-batches before the last)."""
    if skip and isinstance(module, DistributedDataParallel):
        return module.no_sync()
    return contextlib.nullcontext()


def all_finite(value: torch.Tensor) -> bool:
    """Whether ``value`` is finite on every process (all stop together, none hangs)."""
    finite = torch.isfinite(value.detach()).all().to(torch.float32).reshape(1)
    if dist.is_initialized():
        dist.all_reduce(finite, op=dist.ReduceOp.MIN)
    return bool(finite.item())


def mean_over_processes(values: dict[str, float], device: torch.device) -> dict[str, float]:
    """The average of each value over all processes."""
    if not dist.is_initialized() or not values:
        return values
    names = sorted(values)
    stacked = torch.tensor([values[n] for n in names], dtype=torch.float64, device=device)
    dist.all_reduce(stacked)
    return dict(zip(names, (stacked / dist.get_world_size()).tolist(), strict=True))


def barrier() -> None:
    """Waits for every process."""
    if dist.is_initialized():
        dist.barrier()
