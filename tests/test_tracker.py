"""Window ranges, the content-padding rule and the trajectory bookkeeping of the driver."""

from __future__ import annotations

import pytest
import torch

from taptr.model.trajectory import Trajectory
from taptr.windows import content_padding_gap, window_ranges


@pytest.mark.parametrize(
    ("frames", "expected"),
    [
        (8, [(0, 7)]),
        (9, [(0, 7), (1, 8)]),
        (24, [(0, 7), (4, 11), (8, 15), (12, 19), (16, 23)]),
        (26, [(0, 7), (4, 11), (8, 15), (12, 19), (16, 23), (18, 25)]),
        (5, [(0, 4)]),
        (1, [(0, 0)]),
    ],
)
def test_window_ranges(frames, expected):
    assert window_ranges(frames, 8, 4) == expected


def test_window_ranges_50_frames():
    ranges = window_ranges(50, 8, 4)
    assert len(ranges) == 12
    assert ranges[-1] == (42, 49)
    assert ranges[:2] == [(0, 7), (4, 11)]


@pytest.mark.parametrize("frames", range(1, 60))
def test_windows_cover_every_frame_in_order(frames):
    ranges = window_ranges(frames, 8, 4)
    covered = set()
    for first, last in ranges:
        assert last - first + 1 == min(8, frames)
        covered.update(range(first, last + 1))
    assert covered == set(range(frames))
    assert [r[1] for r in ranges] == sorted(r[1] for r in ranges)
    assert ranges[-1][1] == frames - 1


def test_window_ranges_reject_empty_video():
    with pytest.raises(ValueError, match="at least one frame"):
        window_ranges(0, 8, 4)


def test_content_padding_gap():
    assert content_padding_gap(24, 24, training=False) == 1
    assert content_padding_gap(47, 24, training=False) == 1
    assert content_padding_gap(48, 24, training=False) == 2
    assert content_padding_gap(100, 24, training=False) == 4
    assert content_padding_gap(100, 24, training=True) == 1
    assert content_padding_gap(None, 24, training=False) == 1


def test_trajectory_write_pad_and_release():
    initial = torch.zeros(1, 2, 1)
    trajectory = Trajectory(initial)
    values = torch.arange(1, 5, dtype=torch.float32).view(1, 4, 1, 1).expand(1, 4, 2, 1)
    mask = torch.tensor([[[True, False]] * 4])
    trajectory.write(2, values, mask)  # frames 2..5, point 0 only
    assert trajectory.read(0, 6)[0, :, 0, 0].tolist() == [0, 0, 1, 2, 3, 4, 0]
    assert trajectory.read(0, 6)[0, :, 1, 0].tolist() == [0] * 7
    trajectory.pad_from(5)
    assert trajectory.read(6, 9)[0, :, 0, 0].tolist() == [4, 4, 4, 4]
    released = trajectory.release(before=3)
    assert len(released) == 3 and trajectory.first == 3
    with pytest.raises(IndexError, match="released"):
        trajectory.read(2, 4)
    trajectory.fill(torch.tensor([[False, True]]), torch.full((1, 2, 1), 7.0))
    assert trajectory.read(3, 12)[0, :, 1, 0].tolist() == [7.0] * 10


@pytest.mark.parametrize(("size", "stride"), [(8, 4), (8, 8), (5, 2), (3, 1), (8, 7)])
def test_windows_cover_every_frame_for_other_sizes(size, stride):
    for frames in range(1, 60):
        ranges = window_ranges(frames, size, stride)
        assert set().union(*(range(a, b + 1) for a, b in ranges)) == set(range(frames))
        assert all(b - a + 1 == min(size, frames) for a, b in ranges)
        assert ranges[-1][1] == frames - 1
