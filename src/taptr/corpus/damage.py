"""Damaged parts found and removed before a run: the index it plans from is sound.

A part is trusted when its index file passes `taptr.corpus.index_check` and each of its
tables (tracks, failures) is there, reads as Parquet, has that table's columns and schema
version, holds the rows its index counts, and its least and greatest video id are those
its index names, all read from the footer (the row groups' statistics), not the rows.
What this cannot see: a value edited inside a file that keeps its columns, its row count
and its first and last id (a changed position, an id between them swapped), which only
reading and checking every row would find; compaction, which reads the rows of the parts
it rewrites, checks each video's rows there.

A damaged part is removed whole (its index first, then its tables, each by the part's own
name), one line saying which file and what is wrong; the videos only it held are then
not done, and the run tracks them again. Tables no sound entry names (their index gone,
or naming none of their kind) are removed too, so that the dataset pandas reads is
exactly what the index says. Exact copies of entries in an index file are mended: the
file is written again with each entry once.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from taptr.corpus.index_check import DamagedError, IndexPart, check_schema
from taptr.corpus.layout import FAILURES, FOOTER_READERS, INDEX, TRACKS, ResultLayout
from taptr.corpus.records import DONE
from taptr.corpus.schema import failures_schema, index_schema, tracks_schema
from taptr.corpus.storage import StoreError

if TYPE_CHECKING:
    import pyarrow as pa
    import pyarrow.parquet as pq

MAX_LINES = 10
"""Damaged parts named one per line; more are counted in one line."""


def sound_index(layout: ResultLayout, print_line: Callable[..., Any] = print) -> pa.Table:
    """The entries of the parts that read back as their index says; the others removed.

    Only when no actor is writing (before a run).

    Args:
        layout: OUT.
        print_line: where the lines naming damaged and mended files go.

    Raises:
        StoreError: the store did not answer (nothing is removed on its account).
    """
    import pyarrow as pa

    read = layout.index_parts()
    problems = {p.part: f"{layout.file(INDEX, p.part)} {p.problem}" for p in read if p.problem}
    sound = [part for part in read if part.entries is not None]
    problems.update(_table_problems(layout, sound))
    lines = []
    for part, problem in sorted(problems.items()):
        layout.remove_part(part)
        lines.append(f"removed a damaged part: {problem}; the videos only it held count as not "
                     "done")  # fmt: skip
    kept = [part for part in sound if part.part not in problems]
    for part in kept:
        if part.copies:
            layout.publish(INDEX, part.part, part.entries)
            lines.append(
                f"{layout.file(INDEX, part.part)} gave {part.copies} entries more than once; "
                "written again with each once"
            )
    _say(lines, print_line)
    entries = pa.concat_tables([part.entries for part in kept]) if kept else None
    entries = index_schema().empty_table() if entries is None else entries
    layout.remove_unnamed(entries)
    return entries


def _table_problems(layout: ResultLayout, sound: list[IndexPart]) -> dict[str, str]:
    """Per part whose tracks or failures do not hold what its index says: what is wrong."""
    import pyarrow.compute as pc

    checks = []
    for part in sound:
        assert part.entries is not None
        done = pc.equal(part.entries["status"], DONE)
        for folder, mine in ((TRACKS, done), (FAILURES, pc.invert(done))):
            entries = part.entries.filter(mine)
            if len(entries):
                ids = pc.min_max(entries["video_id"]).as_py()
                counted = Counted(pc.sum(entries["rows"]).as_py(), ids["min"], ids["max"])
                checks.append((part.part, folder, counted))
    with ThreadPoolExecutor(FOOTER_READERS) as pool:
        found = list(pool.map(lambda check: _table_problem(layout, *check), checks))
    problems: dict[str, str] = {}
    for (part, _, _), problem in zip(checks, found, strict=True):
        if problem is not None:
            problems.setdefault(part, problem)
    return problems


@dataclass(frozen=True)
class Counted:
    """What an index says one of its part's tables holds.

    Attributes:
        rows: the rows of its entries; first, last: the least and greatest video id.
    """

    rows: int
    first: str
    last: str


def _table_problem(layout: ResultLayout, part: str, folder: str, counted: Counted) -> str | None:
    """What is wrong with a part's table, by its footer (None: it holds what is counted).

    The footer says the rows, the columns and each row group's least and greatest video
    id: a table of another part (other ids) is found without reading a row.
    """
    relative = layout.file(folder, part)
    try:
        footer = layout.storage.footer(relative)
    except StoreError:
        raise
    except FileNotFoundError:
        return f"{relative} is missing"
    except ValueError:  # ArrowInvalid: cut short, or not Parquet at all
        return f"{relative} does not read as a Parquet file (cut short or replaced)"
    expected = tracks_schema() if folder == TRACKS else failures_schema()
    try:
        check_schema(footer.schema.to_arrow_schema(), expected, f"the {folder} table")
    except DamagedError as error:
        return f"{relative} {error}"
    if footer.num_rows != counted.rows:
        return f"{relative} holds {footer.num_rows} rows where its index counts {counted.rows}"
    ids = _id_range(footer)
    if ids is not None and ids != (counted.first, counted.last):
        return f"{relative} holds other videos than its index names"
    return None


def _id_range(footer: pq.FileMetaData) -> tuple[str, str] | None:
    """(least, greatest) video id by the row groups' statistics; None where one has none."""
    least, greatest = None, None
    for group in range(footer.num_row_groups):
        stats = footer.row_group(group).column(0).statistics  # video_id is the first column
        if stats is None or not stats.has_min_max:
            return None
        low, high = _text(stats.min), _text(stats.max)
        least = low if least is None else min(least, low)
        greatest = high if greatest is None else max(greatest, high)
    return None if least is None or greatest is None else (least, greatest)


def _text(value: object) -> str:
    return value.decode(errors="replace") if isinstance(value, bytes) else str(value)


def _say(lines: list[str], print_line: Callable[..., Any]) -> None:
    for line in lines[:MAX_LINES]:
        print_line(line, flush=True)
    if len(lines) > MAX_LINES:
        print_line(f"... and {len(lines) - MAX_LINES} more damaged or mended parts", flush=True)
