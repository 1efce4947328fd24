"""Reading a video last frame first, holding one segment of decoded frames at a time.

Tracking before a query frame runs the tracker over the video read backwards. Holding the
whole video for that grows without bound with its length, so the file is read in segments
from its end: one demux pass lists the presentation timestamps (no decoding), then each
segment is decoded from the keyframe before it and handed out in reverse. A container that
cannot seek (or whose timestamps are missing or repeated) is decoded from its start for
every segment instead: slower, same frames.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from itertools import islice
from pathlib import Path

import av
import numpy as np

from taptr.io.video import (
    _check_source,
    _image_files,
    _read_images,
    _reason,
    frame_size_check,
    open_video,
    rgb,
)

SEGMENT_FRAMES = 32
"""Decoded frames held at a time: 32 frames of 1080p are 200 MB."""


def iter_frames_reversed(
    path: str | os.PathLike[str], *, max_frames: int | None = None, segment: int = SEGMENT_FRAMES
) -> Iterator[np.ndarray]:
    """Iterates over the first ``max_frames`` frames of a video, last to first.

    Args:
        path: a video file or a folder of png/jpg images (as `taptr.io.video.iter_frames`).
        max_frames: only the first this many frames (None: all).
        segment: frames decoded and held at a time.

    Returns:
        An iterator of (H, W, 3) uint8 RGB frames, frame T − 1 first.

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: unsupported or unreadable file, no frames, or a bad argument.
    """
    if segment < 1:
        raise ValueError(f"segment must be >= 1, got {segment}")
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    source = _check_source(path)
    if source.is_dir():
        images = _image_files(source)[:max_frames]
        return _read_images(images[::-1])
    return _reversed_video(source, max_frames, segment)


def _reversed_video(source: Path, max_frames: int | None, segment: int) -> Iterator[np.ndarray]:
    stamps = _presentation_times(source)[:max_frames]
    if not stamps:
        raise ValueError(f"no frames in video {source}")
    seekable = None not in stamps and len(set(stamps)) == len(stamps)
    same_size = frame_size_check(source)
    for end in range(len(stamps), 0, -segment):
        start = max(0, end - segment)
        frames = _segment_by_seeking(source, stamps[start:end]) if seekable else None
        if frames is None:  # no timestamps, or the seek landed elsewhere
            frames = _segment_from_start(source, start, end)
        for offset, frame in enumerate(reversed(frames)):
            yield same_size(frame, end - 1 - offset)


def _presentation_times(source: Path) -> list[int | None]:
    """Every frame's timestamp in display order, from the packets alone."""
    with open_video(source) as container:
        stream = container.streams.video[0]
        try:
            stamps = [p.pts for p in container.demux(stream) if p.size]
        except av.error.FFmpegError as error:
            raise ValueError(f"cannot read video {source}: {_reason(error)}") from error
    if None in stamps:
        return stamps
    return sorted(stamps)  # packets come in decoding order (B-frames reorder them)


def _segment_by_seeking(source: Path, wanted: list[int | None]) -> list[np.ndarray] | None:
    """Frames with the ``wanted`` timestamps, decoded from the keyframe before the first."""
    first, last = wanted[0], wanted[-1]
    assert first is not None and last is not None
    keep = set(wanted)
    found: list[np.ndarray] = []
    with open_video(source) as container:
        stream = container.streams.video[0]
        try:
            container.seek(first, stream=stream, backward=True, any_frame=False)
            for frame in container.decode(stream):
                if frame.pts is None or frame.pts > last:
                    break
                if frame.pts in keep:
                    found.append(rgb(frame))
        except av.error.FFmpegError:
            return None
    return found if len(found) == len(wanted) else None


def _segment_from_start(source: Path, start: int, end: int) -> list[np.ndarray]:
    with open_video(source) as container:
        stream = container.streams.video[0]
        try:
            frames = [rgb(f) for f in islice(container.decode(stream), start, end)]
        except av.error.FFmpegError as error:
            raise ValueError(f"cannot decode video {source}: {_reason(error)}") from error
    if len(frames) != end - start:
        raise ValueError(f"{source}: decoded {start + len(frames)} frames, expected {end}")
    return frames
