"""The deformable-attention kernel a device runs fastest, found by measuring it there.

Both kernels compute the same sums (`taptr.model.ops`), so the choice changes speed only.
On CPU ``gather`` is several times faster (docs/BENCHMARKS.md); on GPUs the balance depends
on the chip and the sizes (``grid_sample`` is one fused CUDA kernel, ``gather`` is
``embedding_bag``), so there the predictor times the model's own encoder on a frame of its
input size with each kernel and keeps the faster one, remembered per machine and shape
(`taptr.runtime.measured`) so that a second run measures nothing.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import torch

from taptr.model.execution import Kernel
from taptr.model.ops import KERNELS
from taptr.model.taptr import TAPTR
from taptr.runtime.measured import best_seconds, choice_key, remembered

CHOICES = ("auto", "measure", *KERNELS)
"""What `choose_kernel` accepts: ``auto``, ``measure`` or a kernel's name."""


def _input_size(model: TAPTR, input_size: tuple[int, int] | None) -> tuple[int, int]:
    """``input_size``, else the model config's (256 × 256 for a model without one)."""
    return input_size or (model.config.input_size if model.config else (256, 256))


@torch.no_grad()
def time_kernels(
    model: TAPTR,
    device: torch.device,
    *,
    input_size: tuple[int, int] | None = None,
    repeats: int = 3,
    clock: Callable[[], float] = time.perf_counter,
) -> dict[str, float]:
    """Seconds per encoder call with each kernel, on one random frame of the input size.

    The backbone and input projections run once outside the clock: they do not depend on
    the kernel. Each kernel runs once to warm up, then the best of ``repeats`` is kept.

    Args:
        model: the network, already on ``device`` (its execution is left as it is: each
            kernel's execution is handed to the encoder).
        device: where it runs.
        input_size: (height, width) of the frame; default: the model config's.
        repeats: timed calls per kernel.
        clock: the timer (injected by tests).

    Returns:
        ``{kernel: seconds}`` for every kernel of `taptr.model.ops.KERNELS`.
    """
    height, width = _input_size(model, input_size)
    dtype = next(model.input_projections.parameters()).dtype  # the trunk may be bfloat16
    frame = torch.randn(1, 3, height, width, device=device, dtype=dtype)
    maps = model.feature_maps(frame)
    seconds = {}
    for kernel in KERNELS:
        execution = dataclasses.replace(model.execution, kernel=kernel)
        seconds[kernel] = best_seconds(
            lambda e=execution: model.encoder(maps, e), device, repeats, clock
        )
    return seconds


def _fastest_kernel(model: TAPTR, device: torch.device, input_size: tuple[int, int] | None) -> str:
    seconds = time_kernels(model, device, input_size=input_size)
    return min(seconds, key=seconds.__getitem__)


def choose_kernel(
    model: TAPTR,
    device: torch.device,
    choice: str = "auto",
    input_size: tuple[int, int] | None = None,
) -> Kernel:
    """Sets the model's deformable-attention kernel for ``device``; returns the kernel.

    Args:
        model: the network on ``device``; its execution keeps every other setting.
        device: where it runs.
        choice: ``auto`` (measure on accelerators once per machine and shape, then
            remember; keep the execution's kernel on CPU), ``measure`` (measure on any
            device, every time), or ``gather`` / ``grid_sample``.
        input_size: (height, width) the model will see; default: the model config's.

    Raises:
        ValueError: for a choice not in `CHOICES`.
    """
    if choice not in CHOICES:
        raise ValueError(f"unknown kernel {choice!r}; choose from {', '.join(CHOICES)}")
    kernel = choice
    if choice == "auto" and device.type == "cpu":
        kernel = model.execution.kernel
    elif choice == "measure":
        kernel = _fastest_kernel(model, device, input_size)
    elif choice == "auto":
        size = _input_size(model, input_size)
        dtype = next(model.input_projections.parameters()).dtype
        shape = f"{size[0]}x{size[1]} {dtype} {model.execution.name}"
        key = choice_key("deformable-attention kernel", device, repr(model.config), shape)
        kernel = remembered(
            key,
            lambda: _fastest_kernel(model, device, input_size),
            valid=lambda value: isinstance(value, str) and value in KERNELS,
        )
    if kernel != model.execution.kernel:
        model.set_execution(dataclasses.replace(model.execution, kernel=kernel))
    return kernel  # type: ignore[return-value]
