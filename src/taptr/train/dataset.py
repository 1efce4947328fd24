"""Training clips in the official order of sampling and augmentation, and their loader.

Every clip is a pure function of (seed, clip index): the index picks the sequence (a fresh
permutation of the sequences each epoch) and seeds the generator of every random choice.
Micro-batch s of process r holds clips (s · world + r) · B ... (s · world + r) · B + B − 1,
so the processes of a data-parallel run together see exactly the clips that one process
with a world-times larger batch would, and a resumed run continues from the next index
without saving any loader state.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from taptr.data import augment
from taptr.data.augment_spatial import pan_and_crop, random_flip, resize
from taptr.data.kubric import list_sequences, read_sequence
from taptr.data.sampling import (
    TrainingClip,
    collate,
    crop_frames,
    first_visible_frames,
    restart_trajectories,
    sample_points,
)
from taptr.train.config import DataConfig
from taptr.types import TrackingSample

MAX_ATTEMPTS = 20


OFFICIAL_FRAME_SIZE = 512
"""Frame side the official augmentation sizes are given for."""


def training_sequences(data: DataConfig) -> list[Path]:
    """The sequence folders of ``data.root`` followed by those of each ``data.extra_roots``.

    Raises:
        ValueError: ``data.root`` is empty, or a folder holds no sequence.
        FileNotFoundError: a folder does not exist.
    """
    if not data.root:
        raise ValueError("data.root is empty: set it to a folder of Kubric-layout sequences")
    return [path for root in (data.root, *data.extra_roots) for path in list_sequences(root)]


def make_clip(
    sample: TrackingSample, data: DataConfig, size: tuple[int, int], rng: np.random.Generator
) -> TrainingClip | None:
    """Cuts, samples points and augments a clip (spec §5.2 steps 1–6), or None to reject it.

    Args:
        sample: a sequence as read (any size).
        data: sampling and augmentation settings.
        size: (height, width) of the model input.
        rng: the only source of randomness.

    Returns:
        The clip at ``size``, or None when fewer than ``data.num_points`` points are
        visible on the first or middle frame, or when no point is visible before the last
        frame.
    """
    picked = sample_points(crop_frames(sample, data.clip_frames, rng), data.num_points, rng)
    if picked is None:
        return None
    # the official pixel sizes (occluders up to 100 px, pads up to 25 px, crop drift up to
    # 15 px per frame) are meant for 512-pixel frames: keep them relative to the frame
    scale = min(picked.video.shape[1:3]) / OFFICIAL_FRAME_SIZE
    occluders = (2, max(3, round(100 * scale)))
    clip = augment.erase(picked, rng, data.eraser_prob, size_bounds=occluders)
    clip = augment.replace(clip, rng, data.replace_prob, size_bounds=occluders)
    clip = augment.jitter_colour(clip, rng, data.colour_prob)
    clip = augment.blur(clip, rng, data.blur_prob)
    clip = augment.mark_outside(clip)
    if data.camera_panning:
        pads = (0, max(1, round(25 * scale)))
        clip = pan_and_crop(clip, rng, size, pad_bounds=pads, max_offset=max(1, round(15 * scale)))
    else:
        clip = resize(clip, size)
    clip = random_flip(clip, rng, data.hflip_prob, data.vflip_prob)
    starts = first_visible_frames(clip.visible)
    visible, starts = restart_trajectories(clip.visible, starts, data.restart_fraction, rng)
    if (starts == clip.video.shape[0] - 1).all():
        return None  # nothing to track (the official code redraws such clips too)
    return TrainingClip(clip.video, clip.tracks, visible, starts)


def held_out_clip(
    sample: TrackingSample, num_points: int, size: tuple[int, int], rng: np.random.Generator
) -> TrainingClip:
    """An evaluation clip: resized, up to ``num_points`` candidate points, no augmentation."""
    sample = resize(sample, size)
    num_frames = sample.video.shape[0]
    candidates = np.flatnonzero(sample.visible[0] | sample.visible[num_frames // 2])
    chosen = np.sort(rng.choice(candidates, min(num_points, candidates.size), replace=False))
    visible = sample.visible[:, chosen]
    return TrainingClip(
        sample.video, sample.tracks[:, chosen], visible, first_visible_frames(visible)
    )


class ClipDataset(Dataset[TrainingClip]):
    """Augmented clips indexed by a global clip index (any non-negative integer).

    Args:
        sequences: Kubric-layout sequence folders.
        data: the data settings.
        size: (height, width) of the model input.
        seed: the run's base seed.
    """

    def __init__(
        self, sequences: list[Path], data: DataConfig, size: tuple[int, int], seed: int
    ) -> None:
        if not sequences:
            raise ValueError("no training sequences")
        self.sequences = sequences
        self.data = data
        self.size = size
        self.seed = seed

    def __len__(self) -> int:
        return len(self.sequences)

    def sequence_of(self, index: int) -> int:
        """The sequence of clip ``index``: epoch ``index // n`` visits a new permutation."""
        epoch, position = divmod(index, len(self.sequences))
        order = np.random.default_rng((self.seed, epoch, 1)).permutation(len(self.sequences))
        return int(order[position])

    def __getitem__(self, index: int) -> TrainingClip:
        rng = np.random.default_rng((self.seed, index))
        choice = self.sequence_of(index)
        for _ in range(MAX_ATTEMPTS):
            sample = read_sequence(self.sequences[choice], bgr=self.data.bgr)
            clip = make_clip(resize(sample, self.data.frame_size), self.data, self.size, rng)
            if clip is not None:
                return clip
            choice = int(rng.integers(len(self.sequences)))  # another clip, as the official
        raise ValueError(
            f"{MAX_ATTEMPTS} clips in a row (the last: {self.sequences[choice]}) had fewer than "
            f"data.num_points = {self.data.num_points} points visible on their first or middle "
            "frame; lower data.num_points"
        )


class MicroBatchSampler(Sampler[list[int]]):
    """Clip indices of this process's micro-batches ``first .. stop − 1``."""

    def __init__(self, first: int, stop: int, rank: int, world_size: int, batch_size: int):
        self.first, self.stop = first, stop
        self.rank, self.world_size, self.batch_size = rank, world_size, batch_size

    def __iter__(self) -> Iterator[list[int]]:
        for step in range(self.first, self.stop):
            start = (step * self.world_size + self.rank) * self.batch_size
            yield list(range(start, start + self.batch_size))

    def __len__(self) -> int:
        return max(0, self.stop - self.first)


def clip_loader(
    dataset: ClipDataset, sampler: MicroBatchSampler, num_workers: int
) -> DataLoader[TrainingClip]:
    """Batches of `taptr.data.sampling.ClipBatch`, in the sampler's order."""
    if num_workers:
        # A forked worker inherits OpenCV's thread pool in a broken state and can hang in
        # it; without a pool (as detectron2 and mmcv do) OpenCV runs serially everywhere.
        cv2.setNumThreads(0)
    return DataLoader(
        dataset,
        batch_sampler=sampler,
        num_workers=num_workers,
        collate_fn=collate,
        pin_memory=torch.cuda.is_available(),
        # the loader draws a seed when iterated; its own generator keeps that draw out of
        # the global stream (dropout masks), so a resumed run continues exactly
        generator=torch.Generator().manual_seed(dataset.seed),
    )


def held_out_clips(
    sequences: list[Path], data: DataConfig, size: tuple[int, int], seed: int
) -> Iterator[TrainingClip]:
    """The held-out clips, read one at a time; the same points at every evaluation."""
    for index, folder in enumerate(sequences):
        sample = read_sequence(folder, bgr=data.bgr)
        yield held_out_clip(sample, data.num_points, size, np.random.default_rng((seed, index)))
