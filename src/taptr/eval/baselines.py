"""Baseline trackers every report can be compared with: ``static`` and ``lk``.

``static`` leaves every point at its query position, always visible: the score of doing
nothing, which on TAP-Vid is far from zero. ``lk`` is OpenCV's pyramidal Lucas–Kanade
optical flow, chained frame to frame from each query frame on, with a forward-backward check:
a step whose backward flow does not come back near its start marks the point occluded, and an
occluded point waits at its last trusted position until the check passes again.
"""

from __future__ import annotations

import cv2
import numpy as np

from taptr.eval.trackers import query_frames


class StaticTracker:
    """Every point stays at its query position, visible on every frame."""

    bidirectional = True

    def track(self, video: np.ndarray, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tracks that never move.

        Args:
            video: (T, H, W, 3) uint8 frames (only T is used).
            queries: (N, 3) float (t, x, y), frame index and pixels.

        Returns:
            tracks (T, N, 2) (x, y) pixels and visible (T, N) bool, all True.
        """
        num_frames, points = video.shape[0], len(queries)
        tracks = np.broadcast_to(
            np.asarray(queries, dtype=np.float32)[None, :, 1:], (num_frames, points, 2)
        )
        return tracks.copy(), np.ones((num_frames, points), dtype=bool)


class LucasKanadeTracker:
    """Pyramidal Lucas–Kanade (OpenCV) with a forward-backward occlusion check.

    Points are followed forward from their query frame only; frames before it hold the
    query position (``strided`` evaluation adds a reversed pass for them).

    Args:
        window: side of the square integration window, in pixels.
        levels: pyramid levels above the full-resolution image.
        max_backward_error: the largest distance in pixels between a point and the result of
            tracking it one frame forward and back again, for the step to be trusted.
    """

    bidirectional = False

    def __init__(
        self, *, window: int = 21, levels: int = 3, max_backward_error: float = 1.0
    ) -> None:
        self.window = window
        self.levels = levels
        self.max_backward_error = max_backward_error

    def _flow(
        self, source: np.ndarray, target: np.ndarray, points: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Where (K, 2) (x, y) pixels of gray ``source`` are in ``target``, and (K,) success."""
        start = points.reshape(-1, 1, 2).astype(np.float32)
        moved, status, _ = cv2.calcOpticalFlowPyrLK(
            source,
            target,
            start,
            start.copy(),  # output buffer only (no OPTFLOW_USE_INITIAL_FLOW)
            winSize=(self.window, self.window),
            maxLevel=self.levels,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
        )
        return np.asarray(moved).reshape(-1, 2), np.asarray(status).reshape(-1).astype(bool)

    def track(self, video: np.ndarray, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tracks points forward from their query frames.

        Args:
            video: (T, H, W, 3) uint8 RGB frames.
            queries: (N, 3) float (t, x, y), frame index and pixels (centres at integers,
                OpenCV's convention too).

        Returns:
            tracks (T, N, 2) float32 (x, y) pixels and visible (T, N) bool.
        """
        num_frames, height, width = video.shape[:3]
        starts = query_frames(queries)
        position = np.asarray(queries, dtype=np.float32)[:, 1:].copy()  # (N, 2) last trusted
        tracks = np.repeat(position[None], num_frames, axis=0)
        visible = np.ones((num_frames, len(queries)), dtype=bool)
        gray = cv2.cvtColor(video[0], cv2.COLOR_RGB2GRAY)
        for frame in range(1, num_frames):
            previous, gray = gray, cv2.cvtColor(video[frame], cv2.COLOR_RGB2GRAY)
            active = np.flatnonzero(starts < frame)
            if active.size == 0:
                continue
            moved, ok = self._flow(previous, gray, position[active])
            back, back_ok = self._flow(gray, previous, moved)
            error = np.linalg.norm(back - position[active], axis=-1)
            inside = (
                (moved[:, 0] >= -0.5)
                & (moved[:, 0] <= width - 0.5)
                & (moved[:, 1] >= -0.5)
                & (moved[:, 1] <= height - 0.5)
            )
            trusted = ok & back_ok & (error <= self.max_backward_error) & inside
            position[active[trusted]] = moved[trusted]
            tracks[frame, active] = position[active]
            visible[frame, active] = trusted
        return tracks, visible
