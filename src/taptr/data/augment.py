"""Photometric augmentations of training clips (spec §5.2 step 2), as pure functions.

Every function takes a `TrackingSample` (video (T, H, W, 3) uint8 RGB, tracks (T, N, 2)
pixels with centres at integers, visible (T, N)) and a numpy generator, and returns a new
sample; the input is never modified. None of them moves pixels, so tracks never change;
the occluder augmentations (erase, replace) paste rectangles over frames 1..T−1 and mark
the points whose pixel (the one containing the point: ``round(x), round(y)``) they cover
as not visible. Frame 0 is left alone so that every point sampled there keeps its query.
Default values are the official ones (CoTracker's photometric augmentation).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from taptr.types import TrackingSample

Rectangle = tuple[int, int, int, int]
"""Pixel columns x0..x1−1 and rows y0..y1−1: (x0, y0, x1, y1)."""


def mark_outside(sample: TrackingSample) -> TrackingSample:
    """Marks points outside [0, W − 1] × [0, H − 1] as not visible."""
    height, width = sample.video.shape[1:3]
    x, y = sample.tracks[..., 0], sample.tracks[..., 1]
    inside = (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
    return dataclasses.replace(sample, visible=sample.visible & inside)


def _rectangles(
    rng: np.random.Generator, height: int, width: int, max_count: int, bounds: tuple[int, int]
) -> list[Rectangle]:
    """1..max_count rectangles with sides in [bounds[0], bounds[1]), clipped to the image."""
    rectangles = []
    for _ in range(int(rng.integers(1, max_count + 1))):
        cx, cy = rng.integers(0, width), rng.integers(0, height)
        dx, dy = rng.integers(bounds[0], bounds[1], 2)
        x0, x1 = int(np.clip(cx - dx / 2, 0, width - 1)), int(np.clip(cx + dx / 2, 0, width - 1))
        y0, y1 = int(np.clip(cy - dy / 2, 0, height - 1)), int(np.clip(cy + dy / 2, 0, height - 1))
        if x1 > x0 and y1 > y0:
            rectangles.append((x0, y0, x1, y1))
    return rectangles


def covered(tracks: np.ndarray, rectangle: Rectangle) -> np.ndarray:
    """Which points (N, 2) lie on a pixel of the rectangle, (N,) bool."""
    x0, y0, x1, y1 = rectangle
    col, row = np.round(tracks[:, 0]), np.round(tracks[:, 1])
    return (col >= x0) & (col < x1) & (row >= y0) & (row < y1)


def erase(
    sample: TrackingSample,
    rng: np.random.Generator,
    prob: float = 0.5,
    max_rectangles: int = 10,
    size_bounds: tuple[int, int] = (2, 100),
) -> TrackingSample:
    """Occluders: rectangles filled with their mean colour (CoTracker's eraser).

    On each frame after the first, with probability ``prob``, 1..``max_rectangles``
    rectangles with sides in ``size_bounds`` are filled and the points on them marked not
    visible.
    """
    video, visible = sample.video.copy(), sample.visible.copy()
    height, width = video.shape[1:3]
    for t in range(1, video.shape[0]):
        if rng.random() >= prob:
            continue
        for x0, y0, x1, y1 in _rectangles(rng, height, width, max_rectangles, size_bounds):
            region = video[t, y0:y1, x0:x1]
            region[...] = region.reshape(-1, 3).mean(0).round().astype(np.uint8)
            visible[t] &= ~covered(sample.tracks[t], (x0, y0, x1, y1))
    return dataclasses.replace(sample, video=video, visible=visible)


def replace(
    sample: TrackingSample,
    rng: np.random.Generator,
    prob: float = 0.5,
    max_rectangles: int = 10,
    size_bounds: tuple[int, int] = (2, 100),
) -> TrackingSample:
    """Occluders cut from elsewhere in the clip (CoTracker's replace augmentation).

    On each frame after the first, with probability ``prob``, 1..``max_rectangles``
    rectangles with sides in ``size_bounds`` are pasted from random places and frames of a
    twice colour-jittered copy of the clip, and the points on them marked not visible.
    """
    video, visible = sample.video.copy(), sample.visible.copy()
    num_frames, height, width = video.shape[:3]
    fires = np.asarray(rng.random(num_frames) < prob)
    fires[0] = False
    if not fires.any():
        return sample
    source = jitter_colour(jitter_colour(sample, rng, prob=1.0), rng, prob=1.0).video
    for t in np.flatnonzero(fires):
        for x0, y0, x1, y1 in _rectangles(rng, height, width, max_rectangles, size_bounds):
            h, w = y1 - y0, x1 - x0
            sy, sx = rng.integers(0, height - h), rng.integers(0, width - w)
            video[t, y0:y1, x0:x1] = source[rng.integers(num_frames), sy : sy + h, sx : sx + w]
            visible[t] &= ~covered(sample.tracks[t], (x0, y0, x1, y1))
    return dataclasses.replace(sample, video=video, visible=visible)


def _gray(image: np.ndarray) -> np.ndarray:
    """ITU-R 601 luma of (H, W, 3) RGB floats, (H, W)."""
    return image @ np.array([0.299, 0.587, 0.114], np.float32)


def _jitter_frame(
    frame: np.ndarray, rng: np.random.Generator, strengths: tuple[float, float, float, float]
) -> np.ndarray:
    """One frame through torchvision's ColorJitter: four changes in a random order, clamped."""
    brightness, contrast, saturation, hue = strengths
    image: np.ndarray = frame.astype(np.float32) / 255
    for op in rng.permutation(4):
        if op == 0:
            image = image * rng.uniform(1 - brightness, 1 + brightness)
        elif op == 1:
            mean = _gray(image).mean()
            image = (image - mean) * rng.uniform(1 - contrast, 1 + contrast) + mean
        elif op == 2:
            gray = _gray(image)[..., None]
            image = (image - gray) * rng.uniform(1 - saturation, 1 + saturation) + gray
        else:
            hsv = cv2.cvtColor(image, cv2.COLOR_RGB2HSV)  # float input: hue in degrees
            hsv[..., 0] = (hsv[..., 0] + 360 * rng.uniform(-hue, hue)) % 360
            image = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
        image = image.clip(0, 1)
    return (image * 255).round().astype(np.uint8)


def jitter_colour(
    sample: TrackingSample,
    rng: np.random.Generator,
    prob: float = 0.25,
    brightness: float = 0.2,
    contrast: float = 0.2,
    saturation: float = 0.2,
    hue: float = 0.25 / 3.14,
) -> TrackingSample:
    """With probability ``prob``, changes the colours of every frame independently.

    Args:
        sample: the clip.
        rng: randomness.
        prob: probability of changing the clip.
        brightness: factor drawn from [1 − b, 1 + b].
        contrast: factor drawn from [1 − c, 1 + c] around the mean luma.
        saturation: factor drawn from [1 − s, 1 + s] around each pixel's luma.
        hue: shift drawn from [−h, h] of a full turn.
    """
    if rng.random() >= prob:
        return sample
    strengths = (brightness, contrast, saturation, hue)
    video = np.stack([_jitter_frame(frame, rng, strengths) for frame in sample.video])
    return dataclasses.replace(sample, video=video)


def blur(
    sample: TrackingSample,
    rng: np.random.Generator,
    prob: float = 0.25,
    kernel: int = 11,
    sigma: tuple[float, float] = (0.1, 2.0),
) -> TrackingSample:
    """With probability ``prob``, Gaussian-blurs every frame with its own σ in ``sigma``."""
    if rng.random() >= prob:
        return sample
    video = np.stack(
        [
            cv2.GaussianBlur(frame, (kernel, kernel), float(rng.uniform(*sigma)))
            for frame in sample.video
        ]
    )
    return dataclasses.replace(sample, video=video)
