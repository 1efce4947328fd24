"""Corpus video lists: a CSV or Parquet table with one row per video.

Columns (only ``path`` is required):

- ``path``: a video file or image folder; relative paths are relative to the video list's folder.
- ``id``: the video's id in the results (default: ``path`` as written in the video list);
  ids are unique.
- ``points``: the video's queries as JSON, ``[[t, x, y], ...]`` (in Parquet also a list of
  lists of numbers), at most `MAX_POINTS_CELL_BYTES` (room for `MAX_POINTS` points).
- ``grid``: track a grid × grid grid instead; ``mask``: an image of the video's size to
  sample points in (relative to the video list's folder); ``query_frame``: their frame.
  Whole numbers, as text, integers or floats (pandas writes a column with a missing value
  as float64: ``2.0`` is 2, NaN is missing).

A row without ``points``, ``grid`` or ``mask`` gets the default queries (the command's
``--points``, ``--grid`` or ``--mask``). Everything is bounded before it is parsed: the
header line, each row, each cell and the nesting of the points.
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from taptr.corpus.inputs import CorpusVideo, QuerySpec, points_tuple
from taptr.messages import printable

VIDEO_LIST_SUFFIXES = (".csv", ".parquet")
"""File suffixes read as video lists rather than videos."""

COLUMNS = ("path", "id", "points", "grid", "mask", "query_frame")
"""Every column a video list may have."""

MAX_POINTS = 100_000
"""Points one ``points`` cell is sized for."""

MAX_POINTS_CELL_BYTES = 8 * 2**20
"""Largest ``points`` cell: 100,000 points of ``[t, x, y]`` with long decimals take 6 MB."""

MAX_TEXT_CELL_CHARS = 4096
"""Largest ``path``, ``id`` or ``mask`` cell (a path's limit on Linux)."""

MAX_HEADER_BYTES = 64 * 1024
"""Longest CSV header line (six column names take 40 bytes)."""

MAX_ROW_BYTES = MAX_POINTS_CELL_BYTES + 64 * 1024
"""Longest CSV line read at once."""


def is_video_list(item: str) -> bool:
    """Whether a command-line item names a video list file."""
    return Path(item).suffix.lower() in VIDEO_LIST_SUFFIXES and Path(item).is_file()


def read_video_list(path: str | Path, default: QuerySpec | None) -> list[CorpusVideo]:
    """The videos a video list lists, in order.

    Args:
        path: a ``.csv`` (UTF-8, header line) or ``.parquet`` file.
        default: queries of rows that give none; None makes such a row an error.

    Raises:
        ValueError: an unknown, missing or repeated column, no rows, a bad row or cell
            (named by its row number), or an id given twice (both rows named).
    """
    video_list = Path(path)
    folder = video_list.parent
    videos: list[CorpusVideo] = []
    first_row: dict[str, int] = {}
    for number, row in _rows(video_list):
        try:
            video = _video(row, folder, default)
        except (ValueError, TypeError) as error:
            raise ValueError(f"video list {video_list} row {number}: {error}") from None
        earlier = first_row.setdefault(video.video_id, number)
        if earlier != number:
            raise ValueError(
                f"video list {video_list}: rows {earlier} and {number} both have the id "
                f"{printable(video.video_id)!r}; give each video an id of its own"
            )
        videos.append(video)
    if not videos:
        raise ValueError(f"video list {video_list} lists no videos")
    return videos


def _rows(video_list: Path) -> Iterator[tuple[int, dict[str, Any]]]:
    """(row number, cells) of each row; the header's row is 1 in a CSV file."""
    try:
        if video_list.suffix.lower() == ".csv":
            yield from _csv_rows(video_list)
        else:
            yield from _parquet_rows(video_list)
    except (OSError, csv.Error, UnicodeDecodeError) as error:
        raise ValueError(f"video list {video_list}: cannot read it ({error})") from None


def _csv_rows(video_list: Path) -> Iterator[tuple[int, dict[str, Any]]]:
    with video_list.open(encoding="utf-8-sig", newline="") as stream, _cell_limit():
        header_line = stream.readline(MAX_HEADER_BYTES + 1)
        if len(header_line) > MAX_HEADER_BYTES:
            raise ValueError(
                f"video list {video_list}: its header line is longer than {MAX_HEADER_BYTES} bytes"
            )
        columns = next(csv.reader([header_line]), [])
        _check_columns(video_list, [name.strip() for name in columns])
        names = [name.strip() for name in columns]
        # every cell as text: ids like 007 stay as written, and points are JSON
        for number, cells in enumerate(csv.reader(_lines(video_list, stream)), 2):
            if len(cells) > len(names):
                raise ValueError(
                    f"video list {video_list} row {number}: {len(cells)} cells for "
                    f"{len(names)} columns"
                )
            yield number, dict(zip(names, cells, strict=False))


def _lines(video_list: Path, stream: IO[str]) -> Iterator[str]:
    """The file's lines, none read longer than `MAX_ROW_BYTES`."""
    number = 1
    while line := stream.readline(MAX_ROW_BYTES + 1):
        number += 1
        if len(line) > MAX_ROW_BYTES:
            raise ValueError(
                f"video list {video_list} line {number} is longer than {MAX_ROW_BYTES} bytes "
                f"(a points cell holds at most {MAX_POINTS_CELL_BYTES} bytes)"
            )
        yield line


@contextlib.contextmanager
def _cell_limit() -> Iterator[None]:
    """The CSV module's cell limit raised to a points cell's for the block."""
    previous = csv.field_size_limit(MAX_POINTS_CELL_BYTES)
    try:
        yield
    finally:
        csv.field_size_limit(previous)


def _parquet_rows(video_list: Path) -> Iterator[tuple[int, dict[str, Any]]]:
    import pyarrow.parquet as pq

    try:
        file = pq.ParquetFile(video_list)
    except ValueError as error:  # ArrowInvalid: not a Parquet file
        raise ValueError(f"video list {video_list}: cannot read it ({error})") from None
    names = file.schema_arrow.names
    _check_columns(video_list, names)
    number = 0
    for batch in file.iter_batches(batch_size=65536):
        columns = {name: batch.column(name).to_pylist() for name in batch.schema.names}
        for index in range(batch.num_rows):
            number += 1
            yield number, {name: values[index] for name, values in columns.items()}


def _check_columns(video_list: Path, columns: list[str]) -> None:
    repeated = sorted({name for name in columns if columns.count(name) > 1})
    if repeated:
        raise ValueError(f"video list {video_list}: the columns {repeated} appear more than once")
    unknown = set(columns) - set(COLUMNS)
    if unknown:
        shown = sorted(printable(name)[:40] for name in unknown)[:5]
        raise ValueError(
            f"video list {video_list}: unknown columns {shown}; known: {', '.join(COLUMNS)}"
        )
    if "path" not in columns:
        raise ValueError(f"video list {video_list} has no 'path' column")


def _video(row: dict[str, Any], folder: Path, default: QuerySpec | None) -> CorpusVideo:
    written = _text(row.get("path"), "path")
    if not written:
        raise ValueError("empty path")
    path = Path(written) if Path(written).is_absolute() else folder / written
    video_id = _text(row.get("id"), "id") or written
    return CorpusVideo(video_id, str(path), _queries(row, folder, default))


def _queries(row: dict[str, Any], folder: Path, default: QuerySpec | None) -> QuerySpec:
    points = _points(row.get("points"))
    grid, mask = _whole(row.get("grid"), "grid"), _text(row.get("mask"), "mask")
    frame = _whole(row.get("query_frame"), "query_frame")
    if points is None and grid is None and not mask:
        if default is None:
            raise ValueError("no points, grid or mask, and no default queries given")
        return default
    mask_path = None
    if mask:
        mask_path = str(Path(mask) if Path(mask).is_absolute() else folder / mask)
    return QuerySpec(
        points=None if points is None else points_tuple(points),
        grid=grid,
        mask=mask_path,
        query_frame=frame or 0,
        mask_stride=default.mask_stride if default is not None else 8,
    )


def _points(value: object) -> object:
    """The ``points`` cell as rows of numbers (None when empty), bounded before parsing."""
    if not isinstance(value, str):
        return value
    if not value.strip():
        return None
    if len(value) > MAX_POINTS_CELL_BYTES:
        raise ValueError(f"points cell is larger than {MAX_POINTS_CELL_BYTES} bytes")
    depth = _nesting(value)
    if depth > 2:
        raise ValueError(f"points nest {depth} levels deep; expected [[t, x, y], ...]")
    try:
        return json.loads(value)
    except ValueError as error:
        raise ValueError(f"points are not JSON rows of three numbers ({error})") from None


def _nesting(text: str) -> int:
    """How deeply brackets nest in ``text`` (outside JSON strings: none are expected)."""
    depth = deepest = 0
    for char in text:
        if char == "[":
            depth += 1
            deepest = max(deepest, depth)
        elif char == "]":
            depth -= 1
    return deepest


def _whole(value: object, column: str) -> int | None:
    """A whole-number cell: text, an integer or an integral float; None when empty or NaN."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return None
    text = str(value).strip()
    if not text or text.lower() == "nan":
        return None
    try:
        number = float(text)
    except ValueError:
        raise ValueError(f"{column} {printable(text)[:40]!r} is not a whole number") from None
    if not number.is_integer():
        raise ValueError(f"{column} {printable(text)[:40]!r} is not a whole number")
    return int(number)


def _text(value: object, column: str) -> str:
    """A text cell, stripped ('' for empty or missing), bounded."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    text = str(value).strip()
    if len(text) > MAX_TEXT_CELL_CHARS:
        raise ValueError(f"{column} is longer than {MAX_TEXT_CELL_CHARS} characters")
    return text
