"""Superseded rows out of a corpus's dataset, once a run's actors have stopped.

A video tracked again has entries in two parts; only its standing ones are kept
(`taptr.corpus.standing`). A part whose every entry is superseded is removed; a part with
some is rewritten without them under a new name, its index last, then the old part is
removed. A run killed in the middle leaves both copies, and the next compaction keeps the
newer name.
"""

from __future__ import annotations

from collections import defaultdict
from typing import TYPE_CHECKING

from taptr.corpus.layout import FAILURES, INDEX, TRACKS, ResultLayout, new_writer, part_name
from taptr.corpus.records import DONE, FAILED
from taptr.corpus.standing import standing

if TYPE_CHECKING:
    import pyarrow as pa


def kept_entries(index: pa.Table) -> dict[str, set[tuple[str, str]]]:
    """Per part, its (video_id, status) entries that stand (parts with none are absent).

    Args:
        index: the index rows (`taptr.corpus.schema.index_schema`).
    """
    kept: dict[str, set[tuple[str, str]]] = defaultdict(set)
    found = standing(index)
    for status, column in ((DONE, "done_part"), (FAILED, "failed_part")):
        rows = zip(found["video_id"].to_pylist(), found[column].to_pylist(), strict=True)
        for video_id, part in rows:
            if part is not None:
                kept[part].add((video_id, status))
    return kept


def compact(layout: ResultLayout, run: str, index: pa.Table | None = None) -> int:
    """Removes superseded rows from the dataset; returns the parts rewritten or removed.

    Args:
        layout: the output folder (no actor writing to it).
        run: the current run (names the rewritten parts).
        index: the folder's index as just read (`ResultLayout.read_index`), if the
            caller holds it; else it is read here.
    """
    import pyarrow.compute as pc

    if index is None:
        index = layout.read_index()
    if len(index) == 0 or pc.count_distinct(index["video_id"]).as_py() == len(index):
        return 0  # each video once: nothing superseded (the common case, checked cheaply)
    kept = kept_entries(index)
    changed = 0
    writer, seq = new_writer(), 0
    for part in sorted(set(index["part"].to_pylist())):
        entries = index.filter(pc.equal(index["part"], part))
        stay = kept.get(part, set())
        if len(stay) == len(entries):
            continue
        if stay:
            _rewrite(layout, part, entries, stay, part_name(run, writer, seq))
            seq += 1
        layout.remove_part(part)
        changed += 1
    return changed


def _rewrite(
    layout: ResultLayout, part: str, entries: pa.Table, stay: set[tuple[str, str]], new: str
) -> None:
    """Publishes the kept rows of ``part`` as the part ``new`` (its index last)."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    storage = layout.storage
    for folder, status in ((TRACKS, DONE), (FAILURES, FAILED)):
        ids = pa.array(sorted(video for video, kind in stay if kind == status), pa.string())
        if len(ids) == 0:
            continue
        with storage.fs.open_input_file(storage.path(layout.file(folder, part))) as stream:
            table = pq.read_table(stream)
        layout.publish(folder, new, table.filter(pc.is_in(table["video_id"], value_set=ids)))
    keep = [
        (video, status) in stay
        for video, status in zip(
            entries["video_id"].to_pylist(), entries["status"].to_pylist(), strict=True
        )
    ]
    moved = entries.filter(pa.array(keep)).drop_columns(["part"])
    moved = moved.append_column("part", pa.array([new] * len(moved), pa.string()))
    layout.publish(INDEX, new, moved)
