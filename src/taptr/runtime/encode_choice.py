"""How many frames per encoder call a machine runs fastest, measured there and remembered.

Every frame is encoded independently (backbone, input projections, encoder), so the number
of frames per call changes speed and memory only. One frame per call keeps a large frame's
intermediates in a CPU's caches; more frames per call pay where the call's fixed cost
dominates: small frames on a CPU, and GPUs, where one frame per call is launch-bound
(measured in docs/BENCHMARKS.md and its log).

The candidates are the powers of two whose frames together stay within a device's pixel
budget (`PIXELS_PER_CALL`); where more than one fits, each is timed on random frames of
the input size and the choice is remembered per machine and shape (`taptr.runtime.measured`).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import torch

from taptr.memory_estimate import trunk_bytes
from taptr.model.ops.dense import product_type
from taptr.model.taptr import TAPTR
from taptr.runtime.measured import TOLERANCE, best_seconds, choice_key, remembered

PIXELS_PER_CALL = {"cpu": 8 * 128 * 128, "other": 16 * 512 * 512}
"""Most pixels one encoder call takes, all its frames together. On the CPU eight 128 × 128
frames (at 512 × 512 one frame, as before this choice existed: its peak memory is
unchanged); on accelerators sixteen 512 × 512 frames (about 2.7 GB of ResNet-50
activations, `taptr.memory_estimate`), and no more than `MEMORY_SHARE` of the device."""

MEMORY_SHARE = 1 / 8
"""Most of an accelerator's memory one encoder call's trunk activations may take."""

MAX_FRAMES_PER_CALL = 16
"""The largest candidate."""


def candidates(
    device: torch.device,
    input_size: tuple[int, int],
    frame_bytes: int = 0,
    device_memory: int | None = None,
) -> list[int]:
    """Frames per call worth timing on ``device`` at ``input_size``: 1, 2, 4, … in budget.

    Args:
        device: where the model runs.
        input_size: (height, width) the model sees.
        frame_bytes: one frame's trunk activations (`taptr.memory_estimate.trunk_bytes`).
        device_memory: the accelerator's memory, None where it is not limited apart.
    """
    budget = PIXELS_PER_CALL["cpu" if device.type == "cpu" else "other"]
    pixels = input_size[0] * input_size[1]
    most = MAX_FRAMES_PER_CALL
    if device_memory is not None and frame_bytes:
        most = min(most, int(device_memory * MEMORY_SHARE // frame_bytes))
    sizes = [1]
    while sizes[-1] * 2 <= most and sizes[-1] * 2 * pixels <= budget:
        sizes.append(sizes[-1] * 2)
    return sizes


def _device_memory(device: torch.device) -> int | None:
    if device.type == "cuda":
        return int(torch.cuda.get_device_properties(device).total_memory)
    return None


@torch.no_grad()
def time_frames_per_call(
    model: TAPTR,
    device: torch.device,
    input_size: tuple[int, int],
    sizes: list[int],
    *,
    repeats: int = 3,
    clock: Callable[[], float] = time.perf_counter,
) -> dict[int, float]:
    """Seconds per frame of `TAPTR.encode_images` at each number of frames per call.

    Each size runs once to warm up, then the best of ``repeats`` calls is kept.
    """
    dtype = next(model.input_projections.parameters()).dtype
    seconds = {}
    for size in sizes:
        frames = torch.randn(size, 3, *input_size, device=device, dtype=dtype)
        call = best_seconds(lambda f=frames: model.encode_images(f), device, repeats, clock)
        seconds[size] = call / size
    return seconds


def fastest(seconds: dict[int, float]) -> int:
    """The fewest frames per call within `TOLERANCE` of the fastest, per frame."""
    best = min(seconds.values())
    return min(size for size, value in seconds.items() if value <= best * (1 + TOLERANCE))


def precision_label(device: torch.device) -> str:
    """The precision the model runs in here: autocast's type, or the CPU's product type."""
    if torch.is_autocast_enabled(device.type):
        return f"autocast {torch.get_autocast_dtype(device.type)}"
    return f"products {product_type()}"


def choose_frames_per_call(
    model: TAPTR,
    device: torch.device,
    input_size: tuple[int, int],
    choice: int | str = "auto",
) -> int:
    """Frames per encoder call for ``model`` on ``device`` at ``input_size``.

    Called inside the context the model will run in (autocast, bfloat16 products), so
    that what is timed, and the key it is remembered under, is that execution.

    Args:
        model: the network, on ``device``.
        device: where it runs.
        input_size: (height, width) the model sees.
        choice: ``auto`` (measured once per machine and shape, then remembered) or a
            number of frames.

    Raises:
        ValueError: for a choice that is neither ``auto`` nor a positive whole number.
    """
    if choice != "auto":
        if isinstance(choice, bool) or not isinstance(choice, int) or choice < 1:
            raise ValueError(f"frames per call must be 'auto' or at least 1, got {choice!r}")
        return choice
    kind = model.config.backbone.kind if model.config else "resnet50"
    frame_bytes = trunk_bytes(kind, *input_size)
    sizes = candidates(device, input_size, frame_bytes, _device_memory(device))
    if len(sizes) == 1:
        return 1
    weights = next(model.input_projections.parameters()).dtype
    trunk = next(model.backbone.parameters()).dtype
    shape = f"{input_size[0]}x{input_size[1]} {weights} trunk {trunk} {precision_label(device)}"
    key = choice_key("frames per encoder call", device, repr(model.config), shape)
    return int(
        remembered(
            key,
            lambda: fastest(time_frames_per_call(model, device, input_size, sizes)),
            valid=lambda value: type(value) is int and value in sizes,
        )
    )
