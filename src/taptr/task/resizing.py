"""Frames to the model's input size, the two ways a model's config can ask for.

- ``"bilinear"``: antialiased bilinear interpolation with half-pixel centres, what taptr's
  own models are trained with: each output pixel i of an axis
  shrunk by s = in / out averages the inputs j around its centre c = s · (i + 0.5) with
  the triangle weights max(0, 1 − |j + 0.5 − c| / max(s, 1)), normalised to sum to one,
  over j in [⌊c − max(s, 1) + 0.5⌋, ⌊c + max(s, 1) + 0.5⌋); width first, then height.
  Written here as one (out, in) weight matrix per axis; `taptr.api.resize` computes the
  same function on the model's device with ``F.interpolate(..., mode="bilinear",
  antialias=True)`` (equal to 3e-6, tests/test_export_v3_loop.py).
- ``"lanczos"``: the official demo's mediapy resize (TAPTRv2-SPEC.md §6): frames become
  float32 values in 0..255, each channel is resized on its own by Pillow's Lanczos filter
  on a float (``'F'``) image, and the result is **not** clipped (the filter's overshoot,
  about −18…292 on sharp edges, is kept) before the division by 255. Bit for bit the
  official model input; `taptr.api.resize` runs this same function.

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


RESIZE_METHODS = ("lanczos", "bilinear")
"""The resize rules a model's config can name (`taptr.config.ResizeKind`)."""


def check_method(method: str) -> str:
    """``method`` when it is one of `RESIZE_METHODS`.

    Raises:
        ValueError: an unknown method.
    """
    if method not in RESIZE_METHODS:
        raise ValueError(f"unknown resize {method!r}; use 'lanczos' or 'bilinear'")
    return method


def lanczos_resize(pixels: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(F, 3, H, W) float32 values in 0..255 → (F, 3, H_m, W_m) / 255: Pillow's Lanczos.

    Not clipped (module docstring).
    """
    from PIL import Image

    height, width = size
    resized = np.empty((*pixels.shape[:2], height, width), np.float32)
    for index in np.ndindex(*pixels.shape[:2]):
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
    check_method(method)
    pixels = frames.transpose(0, 3, 1, 2).astype(np.float32)  # (F, 3, H, W) in 0..255
    if tuple(pixels.shape[-2:]) == tuple(size):
        return np.ascontiguousarray(pixels / np.float32(255))
    if method == "lanczos":
        return lanczos_resize(pixels, size)
    return bilinear_resize(pixels / np.float32(255), size)
