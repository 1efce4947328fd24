"""Denormal floats flushed to zero while a model runs on the CPU.

Products of small weights and small activations can fall below float32's normal range
(1.2e-38); x86 CPUs then take a microcode path tens of times slower per operation (what
that cost a run with the official-format TAPTRv3 weights: docs/BENCHMARKS_LOG.md). Values
that small carry nothing a tracker reads, so inference on the CPU flushes them.
PyTorch has no getter for the setting: it is switched off again on leaving, PyTorch's
default.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


@contextlib.contextmanager
def flushed_denormals(device_type: str) -> Iterator[None]:
    """Flushes denormals to zero inside the block when running on the CPU."""
    if device_type != "cpu" or not torch.set_flush_denormal(True):
        yield
        return
    try:
        yield
    finally:
        torch.set_flush_denormal(False)
