"""Fabricated TAP-Vid data with known motion, shared by the evaluation tests.

A textured background slides right by one pixel per frame under a static grey occluder;
tracked points follow the texture, so their positions are exact integers, and a point is
occluded exactly while it lies under the occluder. The clips are written as a DAVIS-format
pickle (dict of uint8 videos) and as a Kinetics shard (lists of JPEG-encoded frames).
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from taptr.data.tapvid import pixels_to_raster
from taptr.types import TrackingSample

SIZE = 64
OCCLUDER = (slice(36, 52), slice(24, 40))  # rows, columns of the grey square


def make_clip(
    num_frames: int = 12, *, seed: int = 0, occluder: bool = True, name: str = ""
) -> TrackingSample:
    """A (T, 64, 64, 3) clip sliding right 1 px/frame, 12 tracked points on a grid."""
    rng = np.random.default_rng(seed)
    canvas = rng.uniform(0, 255, size=(SIZE, SIZE + num_frames, 3)).astype(np.float32)
    canvas = cv2.GaussianBlur(canvas, (0, 0), 1.2)
    canvas = (255 * (canvas - canvas.min()) / (canvas.max() - canvas.min())).astype(np.uint8)
    # frame t shows canvas columns [T − t, T − t + SIZE): content moves right by t pixels
    video = np.stack([canvas[:, num_frames - t : num_frames - t + SIZE] for t in range(num_frames)])
    xs, ys = np.meshgrid([8.0, 16.0, 24.0, 32.0], [12.0, 28.0, 44.0])
    start = np.stack([xs.ravel(), ys.ravel()], axis=-1)  # (N, 2) on frame 0
    tracks = start[None] + np.arange(num_frames)[:, None, None] * np.array([1.0, 0.0])
    visible = np.ones(tracks.shape[:2], dtype=bool)
    if occluder:
        rows, cols = OCCLUDER
        video[:, rows, cols] = 128
        x, y = tracks[..., 0], tracks[..., 1]
        visible = ~((y >= rows.start) & (y < rows.stop) & (x >= cols.start) & (x < cols.stop))
    return TrackingSample(video, tracks.astype(np.float32), visible, name)


def tapvid_item(sample: TrackingSample, *, jpeg: bool = False) -> dict:
    """The {video, points, occluded} item of a TAP-Vid pickle (raster points)."""
    height, width = sample.video.shape[1:3]
    points = pixels_to_raster(sample.tracks, height, width).transpose(1, 0, 2)
    video = sample.video
    if jpeg:
        frames = []
        for frame in sample.video:
            buffer = io.BytesIO()
            Image.fromarray(frame).save(buffer, format="JPEG", quality=95)
            frames.append(buffer.getvalue())
        video = np.array(frames, dtype=object)
    return {"video": video, "points": points.astype(np.float32), "occluded": ~sample.visible.T}


def write_davis(path: Path, samples: list[TrackingSample]) -> Path:
    """A DAVIS-format pickle: dict name → item."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps({s.name: tapvid_item(s) for s in samples}))
    return path


def write_kinetics_shard(path: Path, samples: list[TrackingSample]) -> Path:
    """A Kinetics shard: list of items with JPEG-encoded frames."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps([tapvid_item(s, jpeg=True) for s in samples]))
    return path


def test_points_follow_the_texture():
    sample = make_clip(occluder=False)
    for t in range(len(sample.video)):
        x, y = sample.tracks[t].astype(int).T
        x0, y0 = sample.tracks[0].astype(int).T
        np.testing.assert_array_equal(sample.video[t, y, x], sample.video[0, y0, x0])


def test_points_under_the_occluder_are_occluded():
    sample = make_clip(num_frames=16)
    assert 0 < (~sample.visible).sum() < sample.visible.size
    x, y = sample.tracks.astype(int).transpose(2, 0, 1)
    grey = (sample.video[np.arange(16)[:, None], y, x] == 128).all(axis=-1)
    np.testing.assert_array_equal(grey, ~sample.visible)
