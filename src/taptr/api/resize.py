"""Resizing frames to the model's input size on the model's device.

The rules are `taptr.task.resizing`'s: ``"lanczos"`` runs its function (Pillow, on the
host) on the frames' values in 0..255; ``"bilinear"`` computes the same antialiased
bilinear interpolation as its numpy weights, here with ``F.interpolate`` on the frames'
device (what taptr's own models are trained with).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from taptr.api.inputs import as_unit_float
from taptr.task.resizing import check_method
from taptr.task.resizing import lanczos_resize as lanczos_pixels


def resize_frames(frames: Tensor, size: tuple[int, int], method: str) -> Tensor:
    """Frames in [0, 1] (or uint8) → float32 frames of ``size`` on the same device.

    Args:
        frames: (F, 3, H, W) uint8, or float in [0, 1].
        size: (H_m, W_m) output size.
        method: ``"lanczos"`` or ``"bilinear"`` (`taptr.task.resizing`).

    Returns:
        (F, 3, H_m, W_m) float32, about [0, 1] (Lanczos overshoot is kept).

    Raises:
        ValueError: an unknown method.
    """
    check_method(method)
    if tuple(frames.shape[-2:]) == tuple(size):
        return as_unit_float(frames)
    if method == "lanczos":
        return lanczos_resize(frames, size)
    return F.interpolate(as_unit_float(frames), size=size, mode="bilinear", antialias=True)


def lanczos_resize(frames: Tensor, size: tuple[int, int]) -> Tensor:
    """Mediapy's resize of float frames (`taptr.task.resizing.lanczos_resize`).

    Args:
        frames: (F, 3, H, W) uint8, or float in [0, 1] (scaled to 0..255 first).
        size: (H_m, W_m) output size.

    Returns:
        (F, 3, H_m, W_m) float32 values / 255, on the frames' device.
    """
    values = frames.detach().to("cpu", torch.float32)
    if frames.is_floating_point():
        values = values * 255
    return torch.from_numpy(lanczos_pixels(values.numpy(), size)).to(frames.device)
