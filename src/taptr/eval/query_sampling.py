"""Query sampling of the TAP-Vid protocol, in the ``first`` and ``strided`` modes.

``first``: one query per track that is visible at least once, on its first visible frame.
``strided``: every 5th frame (0, 5, 10, …) queries every track visible there, so a track is
duplicated once per such frame, and tracks occluded on all of them are never queried. The
order (stride by stride, tracks in file order within a stride) is tapnet's
(TAPVID-PROTOCOL.md §1.5).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

QUERY_STRIDE = 5
"""Frames between query frames in ``strided`` mode."""


class QueryPoints(NamedTuple):
    """The query points of one video and the ground truth each is scored against.

    Attributes:
        queries: (N, 3) float32 (t, x, y): frame index and pixels (centres at integers).
        tracks: (T, N, 2) float32 ground-truth (x, y) pixels of the queried track.
        visible: (T, N) bool ground-truth visibility of the queried track.
    """

    queries: np.ndarray
    tracks: np.ndarray
    visible: np.ndarray


def _select(
    tracks: np.ndarray, visible: np.ndarray, track_ids: np.ndarray, frames: np.ndarray
) -> QueryPoints:
    """Queries of ``track_ids`` on ``frames`` (both (N,) int), at their ground truth."""
    positions = tracks[frames, track_ids]  # (N, 2) ground truth on each query frame
    queries = np.concatenate([frames[:, None].astype(np.float32), positions], axis=1)
    return QueryPoints(
        queries.astype(np.float32),
        tracks[:, track_ids].astype(np.float32),
        visible[:, track_ids].astype(bool),
    )


def sample_queries_first(tracks: np.ndarray, visible: np.ndarray) -> QueryPoints:
    """One query per track, on its first visible frame; never-visible tracks are dropped.

    Args:
        tracks: (T, N, 2) ground-truth (x, y) pixels.
        visible: (T, N) bool ground-truth visibility.
    """
    track_ids = np.flatnonzero(visible.any(axis=0))
    first_visible = np.argmax(visible[:, track_ids], axis=0)
    return _select(tracks, visible, track_ids, first_visible)


def sample_queries_strided(
    tracks: np.ndarray, visible: np.ndarray, stride: int = QUERY_STRIDE
) -> QueryPoints:
    """Queries on frames 0, stride, 2·stride, …: every track visible on such a frame.

    Args:
        tracks: (T, N, 2) ground-truth (x, y) pixels.
        visible: (T, N) bool ground-truth visibility.
        stride: frames between query frames.
    """
    frames, track_ids = [], []
    for frame in range(0, visible.shape[0], stride):
        ids = np.flatnonzero(visible[frame])
        track_ids.append(ids)
        frames.append(np.full(ids.shape, frame))
    return _select(tracks, visible, np.concatenate(track_ids), np.concatenate(frames))


def sample_queries(tracks: np.ndarray, visible: np.ndarray, query_mode: str) -> QueryPoints:
    """Query points for ``query_mode`` (``"first"`` or ``"strided"``), see the module doc.

    Args:
        tracks: (T, N, 2) ground-truth (x, y) pixels.
        visible: (T, N) bool ground-truth visibility.
        query_mode: ``"first"`` or ``"strided"``.
    """
    if query_mode == "first":
        return sample_queries_first(tracks, visible)
    if query_mode == "strided":
        return sample_queries_strided(tracks, visible)
    raise ValueError(f"unknown query mode {query_mode!r}; expected 'first' or 'strided'")
