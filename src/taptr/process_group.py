"""The process group that ``torchrun`` starts, shared by training and evaluation.

Under ``torchrun`` (``WORLD_SIZE`` > 1) every process joins one group: NCCL for CUDA
devices, gloo otherwise. A single process joins nothing, and the collectives below then
do the local thing, so callers read the same either way.
"""

from __future__ import annotations

import os
from typing import Any


def launched_world_size() -> int:
    """Processes ``torchrun`` started (1 without torchrun)."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def join_process_group(cuda: bool) -> bool:
    """Joins the group when several processes were launched and none is joined yet.

    Args:
        cuda: whether this process works on a CUDA device (NCCL) or not (gloo).

    Returns:
        Whether this call created the group (the caller then destroys it).
    """
    import torch.distributed as dist

    if launched_world_size() <= 1 or dist.is_initialized():
        return False
    dist.init_process_group("nccl" if cuda else "gloo")
    return True


def gather_objects(obj: Any) -> list[Any]:
    """Every process's ``obj`` in rank order, on every process (``[obj]`` alone)."""
    import torch.distributed as dist

    if not dist.is_initialized():
        return [obj]
    gathered: list[Any] = [None] * dist.get_world_size()
    dist.all_gather_object(gathered, obj)
    return gathered
