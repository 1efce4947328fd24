"""Sharding an evaluation over the processes ``torchrun`` starts (gloo on CPU, NCCL on GPU).

Video i goes to rank i mod world size; each rank scores its videos and every rank receives
all results, ordered by video index, so the outcome equals a single process's.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from typing import Any, NamedTuple

from taptr.process_group import gather_objects, join_process_group, launched_world_size


class Shard(NamedTuple):
    """This process's place among the evaluating processes.

    Attributes:
        rank: index of this process.
        world_size: number of processes.
    """

    rank: int
    world_size: int

    def owns(self, index: int) -> bool:
        """Whether the video at ``index`` is scored by this process."""
        return index % self.world_size == self.rank

    @property
    def is_main(self) -> bool:
        """The process that writes files and prints."""
        return self.rank == 0


SINGLE_PROCESS = Shard(0, 1)


def resolve_device(device: str | None) -> str:
    """The device of this process: CUDA when available unless named; one GPU per local rank."""
    import torch

    if device is None:
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and launched_world_size() > 1:
        device = f"cuda:{int(os.environ.get('LOCAL_RANK', '0'))}"
    return device


@contextlib.contextmanager
def process_group(device: str) -> Iterator[Shard]:
    """Joins the processes torchrun started (if any) for the duration of the block.

    A process group that already exists (an evaluation inside training) is used and left
    open; one created here is destroyed on exit.

    Args:
        device: this process's device; CUDA devices use NCCL, others gloo.
    """
    if launched_world_size() <= 1:
        yield SINGLE_PROCESS
        return
    import torch
    import torch.distributed as dist

    cuda = torch.device(device).type == "cuda"
    if cuda and not dist.is_initialized():
        torch.cuda.set_device(torch.device(device))
    created = join_process_group(cuda)
    try:
        yield Shard(dist.get_rank(), dist.get_world_size())
    finally:
        if created:
            dist.destroy_process_group()


def gather(items: list[Any], shard: Shard) -> list[Any]:
    """Every process's ``items``, concatenated in rank order, on every process."""
    if shard.world_size == 1:
        return list(items)
    return [item for part in gather_objects(items) for item in part]
