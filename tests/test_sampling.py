"""Point sampling, query frames, restarted trajectories, batching, and the clip pipeline."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from taptr.data.sampling import (
    TrainingClip,
    candidate_points,
    collate,
    crop_frames,
    first_visible_frames,
    restart_trajectories,
    sample_points,
)
from taptr.data.synthetic import SyntheticConfig, make_video
from taptr.train.config import DataConfig
from taptr.train.dataset import ClipDataset, MicroBatchSampler, make_clip
from taptr.types import TrackingSample


def _visibility() -> np.ndarray:
    # T = 5 (middle frame 2), N = 5
    return np.array(
        [
            [1, 0, 0, 0, 0],
            [1, 0, 1, 0, 0],
            [0, 1, 0, 0, 0],
            [1, 1, 1, 1, 0],
            [1, 0, 1, 1, 0],
        ],
        bool,
    )


def test_candidates_are_visible_on_the_first_or_middle_frame():
    assert candidate_points(_visibility()).tolist() == [0, 1]


def test_sample_points_keeps_n_candidates_or_rejects():
    visible = _visibility()
    sample = TrackingSample(
        np.zeros((5, 4, 4, 3), np.uint8), np.random.rand(5, 5, 2).astype(np.float32), visible
    )
    picked = sample_points(sample, 2, np.random.default_rng(0))
    np.testing.assert_array_equal(picked.visible, visible[:, :2])
    np.testing.assert_array_equal(picked.tracks, sample.tracks[:, :2])
    assert sample_points(sample, 3, np.random.default_rng(0)) is None


def test_first_visible_frames_and_never_visible_points():
    assert first_visible_frames(_visibility()).tolist() == [0, 2, 1, 3, 4]


def test_restart_moves_queries_to_visible_frames():
    rng = np.random.default_rng(0)
    visible = rng.random((8, 40)) < 0.6
    visible[:, 0] = False  # never visible: never restarted
    starts = first_visible_frames(visible)
    new_visible, new_starts = restart_trajectories(visible, starts, 0.25, rng)
    moved = np.flatnonzero(new_starts != starts)
    assert 0 < moved.size <= 10 and 0 not in moved
    assert new_visible[new_starts, np.arange(40)][visible.any(0)].all()  # starts are visible
    for point in range(40):
        assert not new_visible[: new_starts[point], point].any()
        np.testing.assert_array_equal(
            new_visible[new_starts[point] :, point], visible[new_starts[point] :, point]
        )
    unchanged, _ = restart_trajectories(visible, starts, 0.0, rng)
    np.testing.assert_array_equal(unchanged, visible)


def test_crop_frames_keeps_a_consecutive_run():
    video = np.arange(6)[:, None, None, None] * np.ones((6, 2, 2, 3), np.uint8)
    tracks = np.arange(6, dtype=np.float32)[:, None, None] * np.ones((6, 3, 2), np.float32)
    sample = TrackingSample(video, tracks, np.ones((6, 3), bool))
    cut = crop_frames(sample, 4, np.random.default_rng(1))
    first = int(cut.video[0, 0, 0, 0])
    assert cut.video[:, 0, 0, 0].tolist() == list(range(first, first + 4))
    assert cut.tracks[:, 0, 0].tolist() == list(range(first, first + 4))
    assert crop_frames(sample, 0, None) is sample and crop_frames(sample, 6, None) is sample


def test_collate_normalises_by_size_minus_one():
    clip = TrainingClip(
        np.zeros((3, 5, 9, 3), np.uint8),
        np.array([[[8.0, 4.0]], [[0.0, 2.0]], [[4.0, 0.0]]], np.float32),
        np.ones((3, 1), bool),
        np.array([1]),
    )
    batch = collate([clip, clip])
    assert batch.video.shape == (2, 3, 3, 5, 9) and batch.video.dtype == torch.uint8
    assert batch.positions[0, :, 0].tolist() == [[1.0, 1.0], [0.0, 0.5], [0.5, 0.0]]
    assert batch.start_frames.tolist() == [[1], [1]]


@pytest.fixture(scope="module")
def synthetic_sample():
    return make_video(
        np.random.default_rng(0),
        SyntheticConfig(height=64, width=64, num_frames=10, num_points=300),
    )


OFF = dict(
    eraser_prob=0.0,
    replace_prob=0.0,
    colour_prob=0.0,
    blur_prob=0.0,
    camera_panning=False,
    hflip_prob=0.0,
    vflip_prob=0.0,
    restart_fraction=0.0,
)


def test_clip_without_augmentation_is_the_sampled_sequence(synthetic_sample):
    data = DataConfig(num_points=50, **OFF)
    clip = make_clip(synthetic_sample, data, (64, 64), np.random.default_rng(0))
    np.testing.assert_array_equal(clip.video, synthetic_sample.video)
    assert clip.tracks.shape == (10, 50, 2)
    np.testing.assert_array_equal(clip.start_frames, first_visible_frames(clip.visible))
    assert (clip.visible[0] | clip.visible[5]).all()
    rng = np.random.default_rng(0)
    assert make_clip(synthetic_sample, DataConfig(num_points=10_000), (64, 64), rng) is None


@pytest.mark.parametrize(
    "setting",
    [
        {"eraser_prob": 1.0},
        {"replace_prob": 1.0},
        {"colour_prob": 1.0},
        {"blur_prob": 1.0},
        {"camera_panning": True},
        {"hflip_prob": 1.0},
        {"vflip_prob": 1.0},
        {"restart_fraction": 0.5},
        {"clip_frames": 6},
    ],
)
def test_every_augmentation_setting_changes_the_clip(synthetic_sample, setting):
    base = DataConfig(num_points=50, **OFF)
    plain = make_clip(synthetic_sample, base, (64, 64), np.random.default_rng(1))
    changed = make_clip(
        synthetic_sample, dataclasses.replace(base, **setting), (64, 64), np.random.default_rng(1)
    )
    differs = [
        not np.array_equal(a, b) for a, b in zip(plain, changed, strict=True) if a.shape == b.shape
    ]
    assert any(differs)


def test_dataset_is_a_function_of_the_index(tmp_path):
    from taptr.data.synthetic import write_dataset

    config = SyntheticConfig(height=48, width=48, num_frames=8, num_points=200)
    folders = write_dataset(tmp_path, 3, config)
    data = DataConfig(num_points=20, frame_size=(48, 48), num_workers=0)
    dataset = ClipDataset(folders, data, (40, 40), seed=5)
    a, b = dataset[7], ClipDataset(folders, data, (40, 40), seed=5)[7]
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    assert a.video.shape == (8, 40, 40, 3)
    assert sorted(dataset.sequence_of(i) for i in range(3)) == [0, 1, 2]  # one epoch
    assert not np.array_equal(dataset[0].tracks, dataset[1].tracks)


def test_micro_batches_of_processes_tile_the_global_batch():
    single = list(MicroBatchSampler(0, 3, rank=0, world_size=1, batch_size=2))
    ranks = [list(MicroBatchSampler(0, 3, rank=r, world_size=2, batch_size=1)) for r in (0, 1)]
    assert single == [[0, 1], [2, 3], [4, 5]]
    assert [a + b for a, b in zip(*ranks, strict=True)] == single
    assert list(MicroBatchSampler(2, 3, 0, 1, 2)) == [[4, 5]]  # resuming skips what was seen
