"""Frames made here, in numpy, to calibrate quantised graphs: no photographs, no torch.

Int8 graphs need the range of every activation they quantise, measured on inputs like the
ones they will see. Frames of plain noise would set those ranges wrong (a backbone's
activations on noise are nothing like its activations on scenes), so these frames are
built of what natural images hold: smooth shading at several scales, flat regions with
sharp edges (rectangles, disks), stripes and fine grain, all in colour. A clip pans and
zooms slowly over one larger canvas, so consecutive frames share content as video does.
Seeded: the same export gets the same calibration, hence the same int8 graphs.
"""

from __future__ import annotations

import numpy as np


def _smooth(rng: np.random.Generator, shape: tuple[int, int], cells: int) -> np.ndarray:
    """Colour noise (H, W, 3) in [0, 1], smooth over ``cells`` cells per side (bilinear)."""
    height, width = shape
    grid = rng.uniform(0, 1, (cells + 1, cells + 1, 3))
    rows = np.linspace(0, cells, height)
    cols = np.linspace(0, cells, width)
    r0 = np.minimum(rows.astype(int), cells - 1)
    c0 = np.minimum(cols.astype(int), cells - 1)
    fr = (rows - r0)[:, None, None]
    fc = (cols - c0)[None, :, None]
    top = grid[r0][:, c0] * (1 - fc) + grid[r0][:, c0 + 1] * fc
    bottom = grid[r0 + 1][:, c0] * (1 - fc) + grid[r0 + 1][:, c0 + 1] * fc
    return top * (1 - fr) + bottom * fr


def _canvas(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """One textured scene (H, W, 3) in [0, 1]: shading, shapes, stripes and grain."""
    height, width = shape
    image = 0.5 * _smooth(rng, shape, 3) + 0.5 * _smooth(rng, shape, 12)
    rows, cols = np.mgrid[0:height, 0:width]
    for _ in range(rng.integers(8, 16)):
        colour = rng.uniform(0, 1, 3)
        cy, cx = rng.uniform(0, height), rng.uniform(0, width)
        size = rng.uniform(0.03, 0.2) * min(height, width)
        if rng.random() < 0.5:
            inside = (np.abs(rows - cy) < size) & (np.abs(cols - cx) < size * rng.uniform(0.5, 2))
        else:
            inside = (rows - cy) ** 2 + (cols - cx) ** 2 < size**2
        if rng.random() < 0.3:  # a striped object: edges at a scale the flat ones lack
            angle, period = rng.uniform(0, np.pi), rng.uniform(3, 12)
            phase = (rows * np.sin(angle) + cols * np.cos(angle)) / period
            stripes = (np.sin(2 * np.pi * phase) > 0)[..., None]
            image = np.where(inside[..., None], np.where(stripes, colour, 1 - colour), image)
        else:
            image = np.where(inside[..., None], colour, image)
    image += rng.normal(0, 0.03, image.shape)  # sensor grain
    return np.clip(image, 0, 1)


def calibration_frames(count: int, size: tuple[int, int], seed: int = 0) -> np.ndarray:
    """``count`` frames (F, 3, H, W) float32 RGB in [0, 1]: clips of 4 frames over scenes.

    Args:
        count: frames, at least 1.
        size: (H, W) of each frame, each at least 8.
        seed: the scenes' and motions' seed.

    Raises:
        ValueError: a count below 1 or a side below 8.
    """
    if count < 1:
        raise ValueError(f"calibration needs at least 1 frame, got {count}")
    height, width = size
    if min(height, width) < 8:
        raise ValueError(f"calibration frames need sides of at least 8 pixels, got {size}")
    rng = np.random.default_rng(seed)
    frames = []
    while len(frames) < count:
        margin = (height // 4, width // 4)
        canvas = _canvas(rng, (height + 2 * margin[0], width + 2 * margin[1]))
        start = rng.uniform(0, 1, 2) * margin
        step = rng.uniform(-1, 1, 2) * np.array(margin) / 4
        for t in range(min(4, count - len(frames))):
            y, x = (np.clip(start + step * t, 0, np.array(margin) * 2)).astype(int)
            frames.append(canvas[y : y + height, x : x + width])
    return np.ascontiguousarray(np.stack(frames).transpose(0, 3, 1, 2), np.float32)
