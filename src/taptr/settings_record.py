"""The settings that change a tracking result, as a JSON-ready record, and its digest.

``taptr track`` keeps the record in each result folder (``settings.json``) and skips a
video whose folder records the settings asked for; ``taptr track-corpus`` hashes it per
video into the settings digest of its rows and skips a video whose index holds that
digest. One record for both, so that the two commands agree on what "the same settings"
means.

Recorded: the model (name or file, and the SHA-256 of the file its weights came from, so a
retrained checkpoint under the same name counts as another model), its visibility
threshold, the queries (the grid, a digest of the listed points, or a digest of the mask
file), and the options that change what is computed or written. Not recorded: where or
how fast the model runs (device, engine, kernel, frames per call, compile, capture), which
give the same tracks up to rounding.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from taptr.api.predictor import Predictor

FORMAT = 1
"""Version of the record; a record of another version never matches."""


def settings_record(
    predictor: Predictor,
    queries: dict[str, Any],
    *,
    dtype: str,
    max_frames: int | None,
    backward: bool,
    trajectories: bool = False,
) -> dict[str, Any]:
    """The record of a run's settings (JSON-ready).

    Args:
        predictor: the model and its settings.
        queries: the `query_record` of the video's queries.
        dtype: the autocast type asked for (``float32``, ``bfloat16``, ``float16``).
        max_frames: frames read at most (None: all).
        backward: whether points are tracked before their query frames too.
        trajectories: whether trajectory images are written (``taptr track``).
    """
    return {
        "format": FORMAT,
        "model": predictor.source,
        "model_sha256": file_digest(predictor.checkpoint_path or predictor.source),
        "visibility_threshold": predictor.visibility_threshold,
        "queries": queries,
        "input_size": list(predictor.input_size),
        "context_points": predictor.context_points,
        "support_points": predictor.support_points,
        "history_frames": predictor.history_frames,
        "dtype": dtype,
        "max_frames": max_frames,
        "backward": bool(backward),
        "trajectories": bool(trajectories),
    }


def query_record(
    points: np.ndarray | None,
    grid: int | None,
    mask: str | None,
    query_frame: int,
    mask_stride: int,
) -> dict[str, Any]:
    """The ``queries`` entry of `settings_record`: listed points, a grid or a mask.

    Args:
        points: (N, 3) listed (t, x, y) queries, or None.
        grid: the grid's side (used when ``points`` is None).
        mask: the mask file (used when both are None).
        query_frame: frame of the grid or mask points.
        mask_stride: spacing of the mask points.
    """
    if points is not None:
        points = np.ascontiguousarray(points, dtype=np.float32)
        return {"points": len(points), "sha256": hashlib.sha256(points.tobytes()).hexdigest()}
    if grid is not None:
        return {"grid": grid, "query_frame": query_frame}
    return {
        "mask_sha256": file_digest(mask),
        "mask_stride": mask_stride,
        "query_frame": query_frame,
    }


def record_digest(record: dict[str, Any]) -> str:
    """16 hex digits of the record's SHA-256 (its keys sorted)."""
    text = json.dumps(record, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def file_digest(path: str | os.PathLike[str] | None) -> str | None:
    """SHA-256 of a file, or None when there is none (an untrained preset).

    Remembered per file, size and modification time: a run over many videos hashes its
    checkpoint (hundreds of megabytes for the paper's weights) once.
    """
    if path is None or not Path(path).is_file():
        return None
    stat = Path(path).stat()
    return _digest(str(Path(path).resolve()), stat.st_size, stat.st_mtime_ns)


@functools.lru_cache(maxsize=16)
def _digest(path: str, size: int, mtime_ns: int) -> str:
    """`taptr.weights.registry.file_sha256`, remembered by path, size and modification time."""
    from taptr.weights.registry import file_sha256

    return file_sha256(path)
