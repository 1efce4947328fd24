"""The sliding-window rules, in plain Python (no torch), shared by every window loop.

The one window driver (`taptr.model.sliding_window`) reads them for the model and for exported
graphs alike (`taptr.export.graph_runner` puts them behind that driver); the export manifest
writes them down, without torch, for loops written in other languages.
"""

from __future__ import annotations


def window_ranges(num_frames: int, size: int, stride: int) -> list[tuple[int, int]]:
    """First and last frame (inclusive) of every window.

    The official rule: ⌊(T − size) / stride⌋ + 1 windows, one more if they stop short of
    the end, and a window running past the end is shifted back to [T − size, T − 1].
    Videos shorter than ``size`` (which the official code rejects) get one window.
    """
    if num_frames < 1:
        raise ValueError(f"need at least one frame, got {num_frames}")
    if num_frames <= size:
        return [(0, num_frames - 1)]
    count = (num_frames - size) // stride + 1
    if size + stride * (count - 1) < num_frames:
        count += 1
    ranges = []
    for k in range(count):
        first = k * stride
        if first + size > num_frames:
            first = num_frames - size
        ranges.append((first, first + size - 1))
    return ranges


def content_padding_gap(num_frames: int | None, long_video_frames: int, training: bool) -> int:
    """Content is copied to future frames after window k iff k % gap == 0.

    The official evaluation copies only after every ⌊T / 24⌋-th window on videos longer
    than 24 frames; otherwise (and in training, and for streams of unknown length) after
    every window.
    """
    if training or num_frames is None or num_frames <= long_video_frames:
        return 1
    return num_frames // long_video_frames
