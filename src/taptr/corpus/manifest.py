"""Corpus manifests: a CSV or Parquet table with one row per video.

Columns (only ``path`` is required):

- ``path``: a video file or image folder; relative paths are relative to the manifest's folder.
- ``id``: the video's id in the results (default: ``path`` as written in the manifest).
- ``points``: the video's queries as JSON, ``[[t, x, y], ...]`` (in Parquet also a list of
  lists of numbers).
- ``grid``: track a grid × grid grid instead; ``mask``: an image of the video's size to
  sample points in (relative to the manifest's folder); ``query_frame``: their frame.

A row without ``points``, ``grid`` or ``mask`` gets the default queries (the command's
``--points``, ``--grid`` or ``--mask``).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

from taptr.corpus.inputs import CorpusVideo, QuerySpec, points_tuple

MANIFEST_SUFFIXES = (".csv", ".parquet")
"""File suffixes read as manifests rather than videos."""

COLUMNS = ("path", "id", "points", "grid", "mask", "query_frame")
"""Every column a manifest may have."""


def is_manifest(item: str) -> bool:
    """Whether a command-line item names a manifest file."""
    return Path(item).suffix.lower() in MANIFEST_SUFFIXES and Path(item).is_file()


def read_manifest(path: str | Path, default: QuerySpec | None) -> list[CorpusVideo]:
    """The videos a manifest lists, in order.

    Args:
        path: a ``.csv`` (UTF-8, header line) or ``.parquet`` file.
        default: queries of rows that give none; None makes such a row an error.

    Raises:
        ValueError: an unknown column, no ``path`` column, or a bad row (named by its number).
    """
    manifest = Path(path)
    rows = _read_table(manifest)
    folder = manifest.parent
    videos = []
    for number, row in enumerate(rows, 1):
        try:
            videos.append(_video(row, folder, default))
        except (ValueError, TypeError) as error:
            raise ValueError(f"manifest {manifest} row {number}: {error}") from None
    return videos


def _read_table(manifest: Path) -> list[dict]:
    try:
        if manifest.suffix.lower() == ".csv":
            # every cell as text: ids like 007 stay as written, and points are JSON
            with manifest.open(encoding="utf-8-sig", newline="") as stream:
                reader = csv.DictReader(stream)
                rows, columns = list(reader), list(reader.fieldnames or [])
        else:
            import pyarrow.parquet as pq

            table = pq.read_table(manifest)
            rows, columns = table.to_pylist(), table.column_names
    except (ValueError, OSError, csv.Error) as error:  # ArrowInvalid is a ValueError
        raise ValueError(f"manifest {manifest}: cannot read it ({error})") from None
    unknown = set(columns) - set(COLUMNS)
    if unknown:
        raise ValueError(
            f"manifest {manifest}: unknown columns {sorted(unknown)}; known: {', '.join(COLUMNS)}"
        )
    if "path" not in columns:
        raise ValueError(f"manifest {manifest} has no 'path' column")
    return rows


def _video(row: dict, folder: Path, default: QuerySpec | None) -> CorpusVideo:
    written = _text(row.get("path"))
    if not written:
        raise ValueError("empty path")
    path = Path(written) if Path(written).is_absolute() else folder / written
    video_id = _text(row.get("id")) or written
    return CorpusVideo(video_id, str(path), _queries(row, folder, default))


def _queries(row: dict, folder: Path, default: QuerySpec | None) -> QuerySpec:
    points, grid, mask = row.get("points"), _text(row.get("grid")), _text(row.get("mask"))
    frame = _text(row.get("query_frame"))
    if isinstance(points, str):
        points = json.loads(points) if points.strip() else None
    if points is None and not grid and not mask:
        if default is None:
            raise ValueError("no points, grid or mask, and no default queries given")
        return default
    mask_path = None
    if mask:
        mask_path = str(Path(mask) if Path(mask).is_absolute() else folder / mask)
    return QuerySpec(
        points=None if points is None else points_tuple(points),
        grid=int(grid) if grid else None,
        mask=mask_path,
        query_frame=int(frame) if frame else 0,
        mask_stride=default.mask_stride if default is not None else 8,
    )


def _text(value: object) -> str:
    """A cell as stripped text ('' for empty or missing)."""
    return "" if value is None else str(value).strip()
