"""What made a result folder of ``taptr track``: the settings that change its files.

Every run writes ``settings.json`` next to its tracks, in the same atomic set, so a folder's
settings always describe the files beside it. When ``taptr track`` over several videos
meets a folder that holds a finished run, it skips that video only if the recorded
settings are the ones asked for now; a folder made with other settings (another model,
other queries, ``--backward``, ...) or by a taptr too old to record them is tracked again.
``--overwrite`` tracks every video again. What is recorded: `taptr.settings_record`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from taptr.io.file_kind import is_regular_file
from taptr.settings_record import query_record, settings_record

if TYPE_CHECKING:
    from taptr.api.predictor import Predictor

SETTINGS_NAME = "settings.json"
"""The file of a result folder that records its settings."""

MAX_SETTINGS_BYTES = 64 * 1024
"""Largest settings file read: a record takes about 600 bytes."""


def track_settings(
    args: argparse.Namespace, predictor: Predictor, listed: np.ndarray | None
) -> dict[str, Any]:
    """The settings of this run that change a result folder's files (JSON-ready)."""
    return settings_record(
        predictor,
        query_settings(args, listed),
        dtype=args.dtype,
        max_frames=args.max_frames,
        backward=args.backward,
        trajectories=args.trajectories,
    )


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
    """The ``queries`` entry of `track_settings`."""
    return query_record(listed, args.grid, args.mask, args.query_frame, args.mask_stride)
