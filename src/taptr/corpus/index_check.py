"""The parts' index read without trusting it: each file checked before its entries count.

OUT is often a shared folder or bucket, so an index file may have been cut, replaced,
copied under another part's name or edited. An index file is taken only when it reads as
Parquet with the index's columns (`taptr.corpus.schema.index_schema`) and schema version,
holds entries, and every entry names the file's own part, a status taptr writes
(``done``, ``failed``), a row count it could have written (≥ 1; 1 for a failure), and no
video twice. (Its ``run`` may be older than the name's: compaction keeps the run that
tracked a video.) Anything else makes the file *damaged*: its entries are dropped whole and
the pipeline removes the part (`taptr.corpus.damage`). Exact copies of an entry (a file
concatenated with itself) are the one thing mended: the entry is kept once.

Names only ever come from the folder's listing, matched against the layout's own pattern
(`taptr.corpus.layout.PART`); a value read from a file (``part``) is compared with that
name and never becomes a path.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from taptr.corpus.records import DONE, FAILED
from taptr.corpus.schema import SCHEMA_KEY, SCHEMA_VERSION, index_schema
from taptr.corpus.storage import Storage, StoreError

if TYPE_CHECKING:
    import pyarrow as pa


class DamagedError(ValueError):
    """A part's file that cannot be trusted; the message says why, naming no path."""


@dataclass(frozen=True)
class IndexPart:
    """One index file as read.

    Attributes:
        part: the part's name (the file's own, from the listing).
        entries: its entries (`index_schema`), each once; None when it is damaged or gone.
        problem: why it is damaged (None when it is sound).
        copies: entries given more than once in the file (each kept once).
    """

    part: str
    entries: pa.Table | None
    problem: str | None = None
    copies: int = 0


def read_index_part(storage: Storage, relative: str, part: str) -> IndexPart:
    """Reads and checks one index file (see the module docstring).

    Args:
        storage: OUT.
        relative: the file inside OUT (``_index/{part}.parquet``).
        part: its part's name.

    Raises:
        StoreError: the store did not answer (a missing file is no error: None entries).
    """
    try:
        table = storage.read_table(relative)
    except FileNotFoundError:  # removed since the folder was listed
        return IndexPart(part, None)
    except StoreError:
        raise
    except ValueError:  # ArrowInvalid: cut short, empty, or not Parquet at all
        return IndexPart(part, None, "does not read as a Parquet file (cut short or replaced)")
    try:
        entries, copies = checked_entries(table, part)
    except DamagedError as error:
        return IndexPart(part, None, str(error))
    return IndexPart(part, entries, copies=copies)


def checked_entries(table: pa.Table, part: str) -> tuple[pa.Table, int]:
    """(the entries, each once; how many were copies) of an index file's table.

    Raises:
        DamagedError: the table is not an index that taptr could have written for ``part``.
    """
    import pyarrow.compute as pc

    check_schema(table.schema, index_schema(), "the index")
    if table.num_rows == 0:
        raise DamagedError("holds no entries")
    if any(column.null_count for column in table.columns):
        raise DamagedError("has empty cells")
    _all_equal(table["part"], part, "names another part")
    status = table["status"]
    if not pc.all(pc.is_in(status, value_set=_strings([DONE, FAILED]))).as_py():
        raise DamagedError(f"has a status other than {DONE} or {FAILED}")
    rows = table["rows"]
    failed = pc.equal(status, FAILED)
    if pc.min(rows).as_py() < 1 or pc.any(pc.and_(failed, pc.not_equal(rows, 1))).as_py():
        raise DamagedError("counts rows a part cannot hold (below 1, or more than 1 for a failure)")
    return _each_once(table)


def check_schema(found: pa.Schema, expected: pa.Schema, what: str) -> None:
    """Refuses columns other than ``expected``'s, or another schema version.

    Raises:
        DamagedError: names the columns found, or the version.
    """
    if not found.remove_metadata().equals(expected.remove_metadata()):
        names = ", ".join(found.names[:8]) + (", ..." if len(found.names) > 8 else "")
        raise DamagedError(f"holds other columns than {what} ({names or 'none'})")
    version = (found.metadata or {}).get(SCHEMA_KEY)
    if version != SCHEMA_VERSION.encode():
        shown = "none" if version is None else repr(version.decode(errors="replace")[:20])
        raise DamagedError(f"has schema version {shown}, not {SCHEMA_VERSION}")


def _all_equal(column: pa.ChunkedArray, value: str, problem: str) -> None:
    import pyarrow.compute as pc

    if not pc.all(pc.equal(column, value)).as_py():
        other = pc.filter(column, pc.not_equal(column, value))[0].as_py()
        raise DamagedError(f"{problem} ({_short(other)})")


def _each_once(table: pa.Table) -> tuple[pa.Table, int]:
    """(entries without exact copies, copies dropped); a video given twice otherwise is damage."""
    import pyarrow as pa

    keys = table.select(["video_id", "status"])
    if keys.group_by(keys.column_names).aggregate([]).num_rows == table.num_rows:
        return table, 0  # the common case, checked without rebuilding the table
    distinct = table.group_by(table.column_names).aggregate([])
    if distinct.select(keys.column_names).group_by(keys.column_names).aggregate([]).num_rows != len(
        distinct
    ):
        raise DamagedError("gives one video twice, with different entries")
    entries = pa.Table.from_arrays(
        [distinct[name] for name in table.column_names], schema=table.schema
    )
    return entries, table.num_rows - entries.num_rows


def _strings(values: list[str]) -> pa.Array:
    import pyarrow as pa

    return pa.array(values, pa.string())


def _short(value: object, limit: int = 60) -> str:
    """A value read from a file, quoted and cut short for a message (ids may be hostile)."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "...'"
