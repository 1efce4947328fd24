"""Pixels in, pixels out over exported graphs, with the predictor's conventions.

`track_video` takes a uint8 video and (t, x, y) pixel queries, resizes frames to the
export's input size window by window, runs `taptr.export.graph_runner.track_points`, and maps the
positions back to the input pixels, with the predictor's forward-only conventions: frames
before a point's query frame are not visible, and each query comes back exactly on its own
frame, visible.

Resizing uses OpenCV (area averaging when shrinking, bilinear when enlarging), close to but
not bit-equal with the predictor's antialiased bilinear resize; frames already at the
input size are used as they are. The window loop is the model's own (it needs torch, on
the CPU; the network runs in the graphs).
"""

from __future__ import annotations

import cv2
import numpy as np

from taptr.export.graph_runner import Steps, track_points
from taptr.export.manifest import ExportManifest


def resize_frames(frames: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(F, H, W, 3) uint8 → (F, 3, H_m, W_m) float32 RGB in [0, 1] at ``size`` (H_m, W_m)."""
    height, width = size
    if frames.shape[1:3] != (height, width):
        shrink = frames.shape[1] > height or frames.shape[2] > width
        method = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
        frames = np.stack([cv2.resize(f, (width, height), interpolation=method) for f in frames])
    return frames.transpose(0, 3, 1, 2).astype(np.float32) / 255


def track_video(
    steps: Steps,
    manifest: ExportManifest,
    video: np.ndarray,
    queries: np.ndarray,
    visibility_threshold: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Tracks (t, x, y) pixel queries through a uint8 video with exported graphs.

    Args:
        steps: the graphs (`taptr.export.graph_steps.load_steps`).
        manifest: the export's description.
        video: (T, H, W, 3) uint8 RGB frames, any size.
        queries: (N, 3) as (t, x, y): frame index and pixel position (pixel centres at
            integers) in the input video.
        visibility_threshold: visible where sigmoid(visibility logit) exceeds it.

    Returns:
        tracks (T, N, 2) float32 (x, y) pixels of the input video and visibility (T, N)
        bool.
    """
    num_frames, height, width = video.shape[:3]
    queries = np.asarray(queries, np.float64).reshape(-1, 3)
    starts = queries[:, 0].round().astype(np.int64)
    if np.any((starts < 0) | (starts >= num_frames)):
        raise ValueError(f"query frames must lie in [0, {num_frames})")
    scale = np.array([max(width - 1, 1), max(height - 1, 1)], np.float64)
    positions = (queries[:, 1:] / scale).astype(np.float32)  # normalised (x, y)

    def load(first: int, last: int) -> np.ndarray:
        return resize_frames(video[first : last + 1], manifest.input_size)

    result = track_points(steps, manifest, load, num_frames, starts, positions)
    tracks = (result.positions * scale).astype(np.float32)  # (T, N, 2) input pixels
    logits = result.visibility_logits[..., 1]  # (T, N), channel 1 = visible
    before = np.arange(num_frames)[:, None] < starts[None]  # (T, N)
    points = np.arange(len(starts))
    tracks[starts, points] = queries[:, 1:]
    visible = 1 / (1 + np.exp(-logits)) > visibility_threshold
    visible[before] = False
    visible[starts, points] = True
    return tracks, visible
