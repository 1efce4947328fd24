"""Fabricated photographs and the check that tracks follow what they show, for the photo tests."""

from __future__ import annotations

import cv2
import numpy as np


def fabricated_photo(seed: int, height: int, width: int, cell: int) -> np.ndarray:
    """A smooth textured (H, W, 3) uint8 'photograph' whose blue channel is zero everywhere.

    ``cell`` is the side in pixels of the noise that is smoothed (larger: smoother).
    """
    rng = np.random.default_rng(seed)
    noise = rng.random((height // cell, width // cell, 2), dtype=np.float32)
    smooth = cv2.resize(noise, (width, height), interpolation=cv2.INTER_CUBIC)
    image = np.zeros((height, width, 3), np.uint8)
    image[..., :2] = (255 * smooth).clip(0, 255).astype(np.uint8)
    return image


def colours_under(video: np.ndarray, tracks: np.ndarray) -> np.ndarray:
    """(T, N, 3) float colours at the rounded track positions, clipped into the frame."""
    frames, height, width = video.shape[:3]
    rows = np.round(tracks[..., 1]).clip(0, height - 1).astype(int)
    cols = np.round(tracks[..., 0]).clip(0, width - 1).astype(int)
    return video[np.arange(frames)[:, None], rows, cols].astype(float)


def colour_drift(colours: np.ndarray, visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How much the colour under each visible point moves from its first visible frame.

    Returns the mean absolute change per visible (frame, point) against the point's own
    first colour, and the same against another point's first colour (the shuffled
    control): tracks that follow the content show a much smaller first than second.
    """
    first = visible.argmax(0)
    same, other = [], []
    for t in range(1, colours.shape[0]):
        both = visible[t] & (first < t)
        start = colours[first[both], np.flatnonzero(both)]
        same.append(np.abs(colours[t, both] - start).mean(1))
        other.append(np.abs(np.roll(colours[t, both], 1, axis=0) - start).mean(1))
    return np.concatenate(same), np.concatenate(other)
