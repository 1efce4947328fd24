"""Geometric augmentations of training clips (spec §5.2 steps 3–5), as pure functions.

Each one moves pixels by a known per-frame affine map and moves the tracks by exactly the
same map, so a track keeps landing on the pixel it followed (pixel centres at integers;
OpenCV's warps and resizes use the same convention). Points that end up outside
[0, W − 1] × [0, H − 1] are marked not visible. Inputs are never modified.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from taptr.data.augment import mark_outside
from taptr.types import TrackingSample


def _warp(sample: TrackingSample, maps: np.ndarray, size: tuple[int, int]) -> TrackingSample:
    """Applies one 2×3 affine per frame to pixels and tracks; zeros outside the source.

    Args:
        sample: the clip.
        maps: (T, 2, 3) maps from source pixels to output pixels.
        size: output (height, width).
    """
    height, width = size
    video = np.stack(
        [
            cv2.warpAffine(
                frame,
                m,
                (width, height),
                flags=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=(0, 0, 0),
            )
            for frame, m in zip(sample.video, maps, strict=True)
        ]
    )
    tracks = np.einsum("tij,tnj->tni", maps[:, :, :2], sample.tracks) + maps[:, None, :, 2]
    moved = dataclasses.replace(sample, video=video, tracks=tracks.astype(np.float32))
    return mark_outside(moved)


def pan_and_crop(
    sample: TrackingSample,
    rng: np.random.Generator,
    size: tuple[int, int],
    pad_bounds: tuple[int, int] = (0, 25),
    scale_range: tuple[float, float] = (0.75, 1.25),
    scale_delta: float = 0.05,
    max_offset: int = 15,
) -> TrackingSample:
    """Simulated camera motion: zoom drifting over time and a drifting crop (PIPs style).

    The clip is zero-padded on each side by [pad_bounds[0], pad_bounds[1]) pixels, scaled
    per frame (a random overall scale plus a smooth per-frame drift, x and y pulled
    together, never smaller than the crop + 10 pixels; the ratio applied is
    (new size − 1) / (old size − 1), as in the official code) and cropped to ``size``
    around the mean first-frame position of the points visible there, with a crop offset
    that drifts by up to ``max_offset`` pixels per frame. Padding, scaling and cropping are
    composed into one affine per frame, so every frame is resampled only once.

    Args:
        sample: the clip.
        rng: randomness.
        size: output (height, width).
        pad_bounds: range of the zero padding per side, in pixels.
        scale_range: range of the overall scale.
        scale_delta: largest per-frame change of the scale.
        max_offset: largest per-frame move of the crop, in pixels.
    """
    num_frames, height, width = sample.video.shape[:3]
    crop_h, crop_w = size
    pad_left, pad_right, pad_top, pad_bottom = rng.integers(pad_bounds[0], pad_bounds[1], 4)
    padded_w, padded_h = width + pad_left + pad_right, height + pad_top + pad_bottom

    scale_x = scale_y = rng.uniform(*scale_range)
    delta = np.zeros(2)
    ratios, sizes = [], []
    for t in range(num_frames):
        if t == 1:
            delta = rng.uniform(-scale_delta, scale_delta, 2)
        elif t > 1:
            delta = 0.8 * delta + 0.2 * rng.uniform(-scale_delta, scale_delta, 2)
        scale_x, scale_y = scale_x + delta[0], scale_y + delta[1]
        mean = (scale_x + scale_y) / 2
        scale_x = float(np.clip(0.5 * scale_x + 0.5 * mean, 0.2, 2.0))
        scale_y = float(np.clip(0.5 * scale_y + 0.5 * mean, 0.2, 2.0))
        new_w = max(int(padded_w * scale_x), crop_w + 10)
        new_h = max(int(padded_h * scale_y), crop_h + 10)
        scale_x, scale_y = (new_w - 1) / (padded_w - 1), (new_h - 1) / (padded_h - 1)
        ratios.append((scale_x, scale_y))
        sizes.append((new_w, new_h))

    anchor = sample.visible[0]
    if anchor.any():
        centre = sample.tracks[0, anchor].mean(0) + (pad_left, pad_top)
        centre = centre * ratios[0]
    else:
        centre = np.array([crop_w, crop_h], np.float64)  # the official fallback
    x0, y0 = int(centre[0] - crop_w // 2), int(centre[1] - crop_h // 2)
    offset = np.zeros(2, np.int64)
    maps = np.zeros((num_frames, 2, 3))
    for t in range(num_frames):
        if t == 1:
            offset = rng.integers(-max_offset, max_offset, 2)
        elif t > 1:
            offset = (0.8 * offset + 0.2 * rng.integers(-max_offset, max_offset + 1, 2)).astype(
                np.int64
            )
        new_w, new_h = sizes[t]
        x0 = int(np.clip(x0 + offset[0], 0, new_w - crop_w - 1))
        y0 = int(np.clip(y0 + offset[1], 0, new_h - crop_h - 1))
        rx, ry = ratios[t]
        maps[t] = [[rx, 0, rx * pad_left - x0], [0, ry, ry * pad_top - y0]]
    return _warp(sample, maps, size)


def flip(sample: TrackingSample, horizontal: bool, vertical: bool) -> TrackingSample:
    """Mirrors every frame; x → W − 1 − x and/or y → H − 1 − y."""
    height, width = sample.video.shape[1:3]
    video, tracks = sample.video, sample.tracks.copy()
    if horizontal:
        video = video[:, :, ::-1]
        tracks[..., 0] = width - 1 - tracks[..., 0]
    if vertical:
        video = video[:, ::-1]
        tracks[..., 1] = height - 1 - tracks[..., 1]
    return dataclasses.replace(sample, video=np.ascontiguousarray(video), tracks=tracks)


def random_flip(
    sample: TrackingSample,
    rng: np.random.Generator,
    horizontal_prob: float = 0.5,
    vertical_prob: float = 0.5,
) -> TrackingSample:
    """Flips the whole clip horizontally and/or vertically with the given probabilities."""
    horizontal, vertical = rng.random(2) < (horizontal_prob, vertical_prob)
    return flip(sample, bool(horizontal), bool(vertical))


def resize(sample: TrackingSample, size: tuple[int, int]) -> TrackingSample:
    """Resizes every frame to (height, width); a no-op at the same size.

    Uses area averaging to shrink and bilinear interpolation to enlarge. Both sample pixel
    centres, so a point moves as x' = (x + 0.5)·W'/W − 0.5 (and likewise y).
    """
    height, width = sample.video.shape[1:3]
    new_h, new_w = size
    if (new_h, new_w) == (height, width):
        return sample
    shrink = new_h * new_w < height * width
    mode = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    video = np.stack([cv2.resize(f, (new_w, new_h), interpolation=mode) for f in sample.video])
    scale = np.array([new_w / width, new_h / height], np.float32)
    tracks = (sample.tracks + 0.5) * scale - 0.5
    return mark_outside(dataclasses.replace(sample, video=video, tracks=tracks))
