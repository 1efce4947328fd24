"""What made a result folder of ``taptr track``: the settings that change its files.

Every run writes ``settings.json`` next to its tracks, in the same atomic set, so a folder's
settings always describe the files beside it. When ``taptr track`` over several videos
meets a folder that holds a finished run, it skips that video only if the recorded
settings are the ones asked for now; a folder made with other settings (another model,
other queries, ``--backward``, ...) or by a taptr too old to record them is tracked again.
``--overwrite`` tracks every video again.

Recorded: the model (name or file, and the SHA-256 of the file its weights came from, named
weights included, so a retrained checkpoint or other weights saved under the same name count
as another model), its visibility threshold, the queries (the
grid, a digest of the listed points, or a digest of the mask file), and the options that
change what is computed or written. Not recorded: where or how fast the model runs
(``--device``, ``--kernel``, ``--frames-per-call``, ``--compile``, ``--capture``), which give
the same tracks up to rounding.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from taptr.io.file_kind import is_regular_file

if TYPE_CHECKING:
    from taptr.api.predictor import Predictor

SETTINGS_NAME = "settings.json"
"""The file of a result folder that records its settings."""

FORMAT = 1
"""Version of the settings record; a record of another version never matches."""

MAX_SETTINGS_BYTES = 64 * 1024
"""Largest settings file read: a record takes about 600 bytes."""


def track_settings(
    args: argparse.Namespace, predictor: Predictor, listed: np.ndarray | None
) -> dict[str, Any]:
    """The settings of this run that change a result folder's files (JSON-ready)."""
    return {
        "format": FORMAT,
        "model": predictor.source,
        "model_sha256": _file_digest(predictor.checkpoint_path or predictor.source),
        "visibility_threshold": predictor.visibility_threshold,
        "queries": query_settings(args, listed),
        "input_size": list(predictor.input_size),
        "context_points": predictor.context_points,
        "support_points": predictor.support_points,
        "history_frames": predictor.history_frames,
        "dtype": args.dtype,
        "max_frames": args.max_frames,
        "backward": bool(args.backward),
        "trajectories": bool(args.trajectories),
    }


def write_settings(folder: Path, settings: dict[str, Any]) -> None:
    """Writes ``settings.json`` into ``folder`` (a staging folder, written atomically)."""
    text = json.dumps(settings, indent=2, sort_keys=True)
    (folder / SETTINGS_NAME).write_text(text + "\n", encoding="utf-8")


def made_with(folder: Path, settings: dict[str, Any]) -> bool:
    """Whether ``folder`` records exactly ``settings`` (False when it records nothing)."""
    path = folder / SETTINGS_NAME
    # a regular file of settings' size only: a FIFO would block, a huge file is not ours
    if not is_regular_file(path):
        return False
    try:
        if path.stat().st_size > MAX_SETTINGS_BYTES:
            return False
        recorded = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):  # deep nesting: not a record of ours
        return False
    # a round trip through JSON, so tuples and lists, ints and floats compare alike
    return recorded == json.loads(json.dumps(settings))


def query_settings(args: argparse.Namespace, listed: np.ndarray | None) -> dict[str, Any]:
    """The ``queries`` entry of `track_settings` (``taptr track-corpus``: one per video)."""
    if listed is not None:
        points = np.ascontiguousarray(listed, dtype=np.float32)
        return {"points": len(points), "sha256": hashlib.sha256(points.tobytes()).hexdigest()}
    if args.grid is not None:
        return {"grid": args.grid, "query_frame": args.query_frame}
    return {
        "mask_sha256": _file_digest(args.mask),
        "mask_stride": args.mask_stride,
        "query_frame": args.query_frame,
    }


def _file_digest(path: str | os.PathLike[str] | None) -> str | None:
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
    """`taptr.hub.file_sha256`, remembered by path, size and modification time."""
    from taptr.hub import file_sha256

    return file_sha256(path)
