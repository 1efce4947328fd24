"""Frames to the export's input size in numpy, the two ways a model's config can ask for.

The torch-free twins of `taptr.api.resize`, equal to it up to float rounding:

- ``"bilinear"``: PyTorch's antialiased bilinear interpolation (``F.interpolate(...,
  mode="bilinear", antialias=True)``, half-pixel centres): each output pixel i of an axis
  shrunk by s = in / out averages the inputs j around its centre c = s · (i + 0.5) with
  the triangle weights max(0, 1 − |j + 0.5 − c| / max(s, 1)), normalised to sum to one,
  over j in [⌊c − max(s, 1) + 0.5⌋, ⌊c + max(s, 1) + 0.5⌋); width first, then height.
  Written as one (out, in) weight matrix per axis.
- ``"lanczos"``: the official demo's mediapy resize: Pillow's Lanczos on each channel as a
  float image in 0..255, not clipped, then divided by 255.

Frames already at the input size are only converted to float32 in [0, 1].
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np


@lru_cache(maxsize=16)
def axis_weights(in_size: int, out_size: int) -> np.ndarray:
    """(out, in) float32 antialiased bilinear weights of one axis (module docstring)."""
    scale = in_size / out_size
    support = max(scale, 1.0)
    weights = np.zeros((out_size, in_size), np.float64)
    for i in range(out_size):
        centre = scale * (i + 0.5)
        low = max(int(centre - support + 0.5), 0)
        high = min(int(centre + support + 0.5), in_size)
        taps = np.arange(low, high)
        row = np.maximum(0.0, 1 - np.abs((taps - centre + 0.5) / support))
        total = row.sum()
        weights[i, low:high] = row / total if total else row
    return weights.astype(np.float32)


def bilinear_resize(frames: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(F, 3, H, W) float32 → (F, 3, H_m, W_m), antialiased bilinear (module docstring)."""
    height, width = size
    if frames.shape[-1] != width:
        frames = frames @ axis_weights(frames.shape[-1], width).T  # (F, 3, H, W_m)
    if frames.shape[-2] != height:
        frames = np.einsum("oi,fciw->fcow", axis_weights(frames.shape[-2], height), frames)
    return np.ascontiguousarray(frames, np.float32)


def lanczos_resize(frames: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(F, 3, H, W) float32 in [0, 1] → (F, 3, H_m, W_m): Pillow's Lanczos, not clipped."""
    from PIL import Image

    height, width = size
    pixels = frames * np.float32(255)
    resized = np.empty((*frames.shape[:2], height, width), np.float32)
    for index in np.ndindex(*frames.shape[:2]):
        image = Image.fromarray(np.ascontiguousarray(pixels[index]))  # mode 'F'
        resized[index] = np.asarray(image.resize((width, height), Image.Resampling.LANCZOS))
    return resized / np.float32(255)


def resize_frames(frames: np.ndarray, size: tuple[int, int], method: str) -> np.ndarray:
    """uint8 frames (F, H, W, 3) → float32 RGB (F, 3, H_m, W_m) in [0, 1] at ``size``.

    Args:
        frames: (F, H, W, 3) uint8.
        size: (H_m, W_m).
        method: ``"bilinear"`` or ``"lanczos"`` (the manifest's ``resize``).

    Raises:
        ValueError: an unknown method.
    """
    unit = frames.transpose(0, 3, 1, 2).astype(np.float32) / np.float32(255)
    if tuple(unit.shape[-2:]) == tuple(size):
        return np.ascontiguousarray(unit)
    if method == "bilinear":
        return bilinear_resize(unit, size)
    if method == "lanczos":
        return lanczos_resize(unit, size)
    raise ValueError(f"unknown resize {method!r}; use 'lanczos' or 'bilinear'")
