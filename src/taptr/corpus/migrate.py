"""Results of the first layout (one Parquet file per video) moved into parts.

taptr 0.1's corpus job wrote ``tracks/{key}.{digest}.parquet`` and
``failures/{key}.{digest}.parquet`` per video, schema version 1 (no frame counts), with
``_attempts/`` and ``_staging/`` beside them. `migrate` gathers them into parts of the
current layout (`taptr.corpus.layout`) with schema version 2: ``decoded_frames`` is the
frames tracked, ``declared_frames`` is null (the old rows did not keep it). The settings
digests are unchanged, so a rerun with the same settings skips the migrated videos.

A part is published (index last) before its old files are removed; a migration stopped
in the middle is finished by running it again, and a video moved twice is kept once by
the next run's compaction.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from taptr.corpus.layout import (
    FAILURES,
    INDEX,
    OLD_LAYOUT_FILE,
    TRACKS,
    ResultLayout,
    new_run,
    new_writer,
    part_name,
)
from taptr.corpus.records import DONE, FAILED
from taptr.corpus.schema import failures_schema, index_schema, tracks_schema

if TYPE_CHECKING:
    import pyarrow as pa

VIDEOS_PER_PART = 1000
"""Old files gathered into one part."""


def migrate(layout: ResultLayout) -> int:
    """Moves every result of the first layout into parts; returns the videos moved."""
    storage = layout.storage
    run, writer = new_run(), new_writer()
    moved = seq = 0
    for folder, status in ((TRACKS, DONE), (FAILURES, FAILED)):
        names = sorted(e.name for e in storage.list(folder) if OLD_LAYOUT_FILE.match(e.name))
        for start in range(0, len(names), VIDEOS_PER_PART):
            batch = names[start : start + VIDEOS_PER_PART]
            tables = [_upgraded(layout, f"{folder}/{name}", status) for name in batch]
            part = part_name(run, writer, seq)
            seq += 1
            _publish(layout, folder, part, tables, status, run)
            for name in batch:
                storage.delete(f"{folder}/{name}")
            moved += len(batch)
    for leftover in ("_attempts", "_staging"):
        storage.delete_folder(leftover)
    return moved


def _upgraded(layout: ResultLayout, relative: str, status: str) -> pa.Table:
    """An old file's rows with the columns of schema version 2."""
    import pyarrow as pa

    table = layout.storage.read_table(relative)
    schema = tracks_schema() if status == DONE else failures_schema()
    nulls = pa.nulls(len(table), pa.int32())
    decoded = table["num_frames"] if status == DONE else nulls
    table = table.append_column("declared_frames", nulls).append_column("decoded_frames", decoded)
    return table.select(schema.names).cast(schema)


def _publish(
    layout: ResultLayout,
    folder: str,
    part: str,
    tables: list[pa.Table],
    status: str,
    run: str,
) -> None:
    """Publishes a part of old videos: the rows, then its index."""
    import pyarrow as pa

    layout.publish(folder, part, pa.concat_tables(tables))
    entries = {
        "video_id": [t["video_id"][0].as_py() for t in tables],
        "settings_digest": [t["settings_digest"][0].as_py() for t in tables],
        "status": [status] * len(tables),
        "rows": [len(t) for t in tables],
        "run": [run] * len(tables),
        "part": [part] * len(tables),
    }
    layout.publish(INDEX, part, pa.Table.from_pydict(entries, schema=index_schema()))
