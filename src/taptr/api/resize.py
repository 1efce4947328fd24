"""Resizing frames to the model's input size, the two ways a model's config can ask for.

- ``"lanczos"``: what the official demo does through mediapy (TAPTRv2-SPEC.md §6): frames
  become float32 values in 0..255, each channel is resized on its own by Pillow's Lanczos
  filter on a float (``'F'``) image, and the result is **not** clipped (the filter's
  overshoot, about −18…292 on sharp edges, is kept) before the division by 255. Bit for bit
  the official model input.
- ``"bilinear"``: antialiased bilinear interpolation in torch (what taptr's own models are
  trained with), on the frames' device.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor

from taptr.api.inputs import as_unit_float


def resize_frames(frames: Tensor, size: tuple[int, int], method: str) -> Tensor:
    """Frames in [0, 1] (or uint8) → float32 frames of ``size`` on the same device.

    Args:
        frames: (F, 3, H, W) uint8, or float in [0, 1].
        size: (H_m, W_m) output size.
        method: ``"lanczos"`` or ``"bilinear"`` (see the module docstring).

    Returns:
        (F, 3, H_m, W_m) float32, about [0, 1] (Lanczos overshoot is kept).
    """
    if tuple(frames.shape[-2:]) == tuple(size):
        return as_unit_float(frames)
    if method == "bilinear":
        return F.interpolate(as_unit_float(frames), size=size, mode="bilinear", antialias=True)
    if method == "lanczos":
        return lanczos_resize(frames, size)
    raise ValueError(f"unknown resize {method!r}; use 'lanczos' or 'bilinear'")


def lanczos_resize(frames: Tensor, size: tuple[int, int]) -> Tensor:
    """Mediapy's resize of float frames: Pillow Lanczos per channel, not clipped.

    Args:
        frames: (F, 3, H, W) uint8, or float in [0, 1] (scaled to 0..255 first).
        size: (H_m, W_m) output size.

    Returns:
        (F, 3, H_m, W_m) float32 values / 255, on the frames' device.
    """
    height, width = size
    values = frames.detach().to("cpu", torch.float32)
    if frames.is_floating_point():
        values = values * 255
    pixels = values.numpy()  # (F, 3, H, W) float32 in 0..255
    resized = np.empty((*pixels.shape[:2], height, width), dtype=np.float32)
    for index in np.ndindex(*pixels.shape[:2]):
        image = Image.fromarray(np.ascontiguousarray(pixels[index]))  # mode 'F'
        resized[index] = np.asarray(image.resize((width, height), Image.Resampling.LANCZOS))
    return torch.from_numpy(resized / np.float32(255)).to(frames.device)
