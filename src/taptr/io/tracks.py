"""Saving tracks for other programs: ``tracks.npz`` for numpy users, ``tracks.csv`` for all.

Both files use the package conventions: positions are (x, y) pixels of the tracked video with
pixel centres at integers, visibility is True (1) where a point is visible, and queries are
(t, x, y). Both are written atomically, so a crash never leaves a half-written file.

``tracks.npz`` holds ``tracks`` (T, N, 2) float32, ``visibility`` (T, N) bool, ``queries``
(N, 3) float32 and ``metadata``, a JSON string (free-form: video name, fps, model, ...).
It loads without pickle. ``tracks.csv`` has the header ``frame,point,x,y,visible`` and one
row per frame and point (T × N rows, frame-major), visible written as 0 or 1.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from taptr.io.atomic import atomic_path

CSV_HEADER = "frame,point,x,y,visible"


@dataclass
class SavedTracks:
    """The content of a ``tracks.npz`` file.

    Attributes:
        tracks: (T, N, 2) float32 (x, y) pixels.
        visibility: (T, N) bool, True where the point is visible.
        queries: (N, 3) float32 (t, x, y): query frame and pixel position of each point.
        metadata: anything JSON can hold, as given to `save_tracks_npz`.
    """

    tracks: np.ndarray
    visibility: np.ndarray
    queries: np.ndarray
    metadata: dict[str, Any]


def save_tracks_npz(
    path: str | os.PathLike[str],
    tracks: np.ndarray,
    visibility: np.ndarray,
    queries: np.ndarray,
    metadata: Mapping[str, Any] | None = None,
) -> Path:
    """Writes tracks, visibility, queries and metadata to a compressed ``.npz`` file.

    Args:
        path: output file; missing folders are created.
        tracks: (T, N, 2) (x, y) pixels.
        visibility: (T, N) bool, True where the point is visible.
        queries: (N, 3) (t, x, y), t a frame index and (x, y) pixels.
        metadata: JSON-serialisable mapping stored as a JSON string.

    Returns:
        The path written.
    """
    tracks, visibility = _checked(tracks, visibility)
    queries = np.asarray(queries, dtype=np.float32)
    if queries.shape != (tracks.shape[1], 3):
        raise ValueError(f"queries must be (N, 3) = ({tracks.shape[1]}, 3), got {queries.shape}")
    text = json.dumps(dict(metadata or {}))
    target = Path(path)
    # Through a file object, so numpy keeps the name instead of appending ".npz".
    with atomic_path(target) as tmp, open(tmp, "wb") as file:
        np.savez_compressed(
            file, tracks=tracks, visibility=visibility, queries=queries, metadata=np.array(text)
        )
    return target


def load_tracks_npz(path: str | os.PathLike[str]) -> SavedTracks:
    """Reads a file written by `save_tracks_npz`."""
    source = Path(path)
    if not source.is_file():
        raise FileNotFoundError(f"tracks file not found: {source}")
    with np.load(source, allow_pickle=False) as data:
        missing = {"tracks", "visibility", "queries", "metadata"} - set(data.files)
        if missing:
            raise ValueError(f"{source} lacks {', '.join(sorted(missing))}")
        return SavedTracks(
            tracks=data["tracks"].astype(np.float32),
            visibility=data["visibility"].astype(bool),
            queries=data["queries"].astype(np.float32),
            metadata=json.loads(str(data["metadata"])),
        )


def save_tracks_csv(
    path: str | os.PathLike[str], tracks: np.ndarray, visibility: np.ndarray
) -> Path:
    """Writes one ``frame,point,x,y,visible`` row per frame and point.

    Coordinates are written with 9 significant digits, enough to read float32 back exactly.

    Args:
        path: output file; missing folders are created.
        tracks: (T, N, 2) (x, y) pixels.
        visibility: (T, N) bool, True where the point is visible.

    Returns:
        The path written.
    """
    tracks, visibility = _checked(tracks, visibility)
    num_frames, num_points = visibility.shape
    frame, point = np.meshgrid(np.arange(num_frames), np.arange(num_points), indexing="ij")
    rows = np.column_stack(
        [
            frame.ravel(),
            point.ravel(),
            tracks[..., 0].ravel(),
            tracks[..., 1].ravel(),
            visibility.ravel(),
        ]
    ).astype(object)  # mixed integer and float columns, one format each
    target = Path(path)
    with atomic_path(target) as tmp:
        np.savetxt(
            tmp,
            rows,
            fmt=("%d", "%d", "%.9g", "%.9g", "%d"),
            delimiter=",",
            header=CSV_HEADER,
            comments="",
        )
    return target


def load_tracks_csv(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Reads a file written by `save_tracks_csv` (rows may come in any order).

    Returns:
        tracks: (T, N, 2) float32 (x, y) pixels.
        visibility: (T, N) bool.

    Raises:
        FileNotFoundError: the file is missing.
        ValueError: wrong header, or rows that do not cover every frame and point once.
    """
    source = Path(path)
    if not source.is_file():
        raise FileNotFoundError(f"tracks file not found: {source}")
    with open(source, encoding="utf-8") as file:
        header = file.readline().strip()
        if header != CSV_HEADER:
            raise ValueError(f"{source}: expected header {CSV_HEADER!r}, got {header!r}")
        table = np.loadtxt(file, delimiter=",", ndmin=2, dtype=np.float64)
    if table.shape[0] == 0:
        return np.zeros((0, 0, 2), np.float32), np.zeros((0, 0), bool)
    frame, point = table[:, 0].astype(np.int64), table[:, 1].astype(np.int64)
    num_frames, num_points = frame.max() + 1, point.max() + 1
    flat = frame * num_points + point
    complete = len(flat) == num_frames * num_points == np.unique(flat).size
    if frame.min() < 0 or point.min() < 0 or not complete:
        raise ValueError(f"{source}: rows must list every frame and point exactly once")
    tracks = np.empty((num_frames * num_points, 2), np.float32)
    visibility = np.empty(num_frames * num_points, bool)
    tracks[flat] = table[:, 2:4]
    visibility[flat] = table[:, 4] != 0
    return tracks.reshape(num_frames, num_points, 2), visibility.reshape(num_frames, num_points)


def _checked(tracks: np.ndarray, visibility: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    tracks = np.asarray(tracks, dtype=np.float32)
    visibility = np.asarray(visibility, dtype=bool)
    if tracks.ndim != 3 or tracks.shape[2] != 2:
        raise ValueError(f"tracks must be (T, N, 2), got {tracks.shape}")
    if visibility.shape != tracks.shape[:2]:
        raise ValueError(f"visibility must be (T, N) = {tracks.shape[:2]}, got {visibility.shape}")
    return tracks, visibility
