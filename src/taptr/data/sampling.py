"""Choosing the points of a training clip, their query frames, and batching clips.

Spec §5.2: a clip keeps a fixed number N of trajectories, drawn among the points visible
on the first or the middle frame; each point's query (start) frame is its first visible
frame; a quarter of the points then restart at a random later visible frame, as if the
query had been given there. Clips with too few candidate points are rejected by the caller.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from taptr.types import TrackingSample


class TrainingClip(NamedTuple):
    """One augmented clip with its queries, in pixels.

    Attributes:
        video: (T, H, W, 3) uint8 RGB.
        tracks: (T, N, 2) float32 true (x, y) pixels, pixel centres at integers.
        visible: (T, N) bool true visibility.
        start_frames: (N,) int64 query frame of each point.
    """

    video: np.ndarray
    tracks: np.ndarray
    visible: np.ndarray
    start_frames: np.ndarray


class ClipBatch(NamedTuple):
    """A batch of clips as tensors, positions normalised by (W − 1, H − 1).

    Attributes:
        video: (B, T, 3, H, W) uint8 RGB.
        positions: (B, T, N, 2) float32 true (x, y), normalised.
        visible: (B, T, N) bool.
        start_frames: (B, N) int64.
    """

    video: Tensor
    positions: Tensor
    visible: Tensor
    start_frames: Tensor

    def to(self, device: torch.device | str) -> ClipBatch:
        """The batch on ``device``."""
        return ClipBatch(*(t.to(device, non_blocking=True) for t in self))


def crop_frames(
    sample: TrackingSample, num_frames: int, rng: np.random.Generator
) -> TrackingSample:
    """A random run of ``num_frames`` consecutive frames (the whole clip if 0 or longer)."""
    total = sample.video.shape[0]
    if num_frames <= 0 or num_frames >= total:
        return sample
    first = int(rng.integers(0, total - num_frames + 1))
    window = slice(first, first + num_frames)
    return dataclasses.replace(
        sample,
        video=sample.video[window],
        tracks=sample.tracks[window],
        visible=sample.visible[window],
    )


def candidate_points(visible: np.ndarray) -> np.ndarray:
    """Indices of the points visible on the first or the middle frame T // 2, (T, N) → (K,).

    The official code concatenates the two lists (a point visible on both frames can be
    drawn twice, as a duplicate trajectory); here each point is a candidate once.
    """
    num_frames = visible.shape[0]
    return np.flatnonzero(visible[0] | visible[num_frames // 2])


def sample_points(
    sample: TrackingSample, num_points: int, rng: np.random.Generator
) -> TrackingSample | None:
    """Keeps ``num_points`` random candidate trajectories, or returns None if too few.

    Args:
        sample: the clip with all its tracks.
        num_points: N.
        rng: randomness.

    Returns:
        The clip with tracks (T, N, 2) and visible (T, N), in their original order.
    """
    candidates = candidate_points(sample.visible)
    if candidates.size < num_points:
        return None
    chosen = np.sort(rng.choice(candidates, num_points, replace=False))
    return dataclasses.replace(
        sample, tracks=sample.tracks[:, chosen], visible=sample.visible[:, chosen]
    )


def first_visible_frames(visible: np.ndarray) -> np.ndarray:
    """Each point's first visible frame, or the last frame if it is never visible, (T, N) → (N,)."""
    num_frames = visible.shape[0]
    first = visible.argmax(axis=0)
    return np.where(visible.any(axis=0), first, num_frames - 1).astype(np.int64)


def restart_trajectories(
    visible: np.ndarray, start_frames: np.ndarray, fraction: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Moves the query of some points to a random visible frame (spec §5.2 step 6).

    ⌊N · fraction⌋ points with at least one visible frame get a new start frame drawn
    among their visible frames; they count as not visible before it (the model neither
    tracks nor supervises them there).

    Args:
        visible: (T, N) bool.
        start_frames: (N,) current query frames.
        fraction: share of the N points to restart (official: 1/4).
        rng: randomness.

    Returns:
        New visible (T, N) and start frames (N,).
    """
    visible, start_frames = visible.copy(), start_frames.copy()
    eligible = np.flatnonzero(visible.any(axis=0))
    count = min(int(visible.shape[1] * fraction), eligible.size)
    for point in rng.choice(eligible, count, replace=False):
        start = int(rng.choice(np.flatnonzero(visible[:, point])))
        start_frames[point] = start
        visible[:start, point] = False
    return visible, start_frames


def collate(clips: list[TrainingClip]) -> ClipBatch:
    """Stacks clips of equal shape into a `ClipBatch` (positions normalised)."""
    height, width = clips[0].video.shape[1:3]
    scale = np.array([max(width - 1, 1), max(height - 1, 1)], np.float32)
    video = torch.from_numpy(np.stack([c.video for c in clips])).permute(0, 1, 4, 2, 3)
    return ClipBatch(
        video.contiguous(),  # (B, T, 3, H, W)
        torch.from_numpy(np.stack([c.tracks / scale for c in clips]).astype(np.float32)),
        torch.from_numpy(np.stack([c.visible for c in clips])),
        torch.from_numpy(np.stack([c.start_frames for c in clips]).astype(np.int64)),
    )
