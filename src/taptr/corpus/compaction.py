"""Superseded rows out of a corpus's dataset, once a run's actors have stopped.

A video tracked again has entries in two parts; only its standing ones are kept
(`taptr.corpus.standing`). A part whose every entry is superseded is removed; a part with
some is rewritten without them under a new name, its index last, then the old part is
removed. A run killed in the middle leaves both copies, and the next compaction keeps the
newer name. The rows of a part being rewritten are read, so each kept video's rows are
counted there against its index: a part that does not hold them is removed whole, named
in one line, rather than rewritten (its videos only it held count as not done).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

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


def compact(
    layout: ResultLayout,
    run: str,
    index: pa.Table | None = None,
    print_line: Callable[..., Any] | None = None,
) -> int:
    """Removes superseded rows from the dataset; returns the parts rewritten or removed.

    Args:
        layout: the output folder (no actor writing to it).
        run: the current run (names the rewritten parts).
        index: the folder's index as just read (`taptr.corpus.damage.sound_index`), if
            the caller holds it; else it is read here.
        print_line: where a part found damaged while it is rewritten is named.
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
            problem = _rewrite(layout, part, entries, stay, part_name(run, writer, seq))
            seq += problem is None
            if problem is not None and print_line is not None:
                print_line(
                    f"removed a damaged part: {problem}; the videos only it held count as not done",
                    flush=True,
                )
        layout.remove_part(part)
        changed += 1
    return changed


def _rewrite(
    layout: ResultLayout, part: str, entries: pa.Table, stay: set[tuple[str, str]], new: str
) -> str | None:
    """Publishes the kept rows of ``part`` as the part ``new`` (its index last).

    Returns:
        None, or what is wrong with the part when a table does not hold each kept
        video's rows as its index counts them (nothing is published then).
    """
    import pyarrow as pa
    import pyarrow.compute as pc

    counts = dict(
        zip(
            zip(entries["video_id"].to_pylist(), entries["status"].to_pylist(), strict=True),
            entries["rows"].to_pylist(),
            strict=True,
        )
    )
    tables = {}
    for folder, status in ((TRACKS, DONE), (FAILURES, FAILED)):
        ids = sorted(video for video, kind in stay if kind == status)
        if not ids:
            continue
        relative = layout.file(folder, part)
        table = layout.storage.read_table(relative)
        table = table.filter(pc.is_in(table["video_id"], value_set=pa.array(ids, pa.string())))
        found = table.group_by("video_id").aggregate([("video_id", "count")]).to_pydict()
        rows = dict(zip(found["video_id"], found["video_id_count"], strict=True))
        if any(rows.get(video) != counts[(video, status)] for video in ids):
            return f"{relative} does not hold the rows its index counts for its videos"
        tables[folder] = table
    for folder, table in tables.items():
        layout.publish(folder, new, table)
    keep = [
        (video, status) in stay
        for video, status in zip(
            entries["video_id"].to_pylist(), entries["status"].to_pylist(), strict=True
        )
    ]
    moved = entries.filter(pa.array(keep)).drop_columns(["part"])
    moved = moved.append_column("part", pa.array([new] * len(moved), pa.string()))
    layout.publish(INDEX, new, moved)
    return None
