"""The files of a corpus's output folder, and every rule about their names.

Layout of ``OUT`` (version 2)::

    tracks/part-{run}-{writer}-{seq}.parquet     rows of many videos (`tracks_schema`)
    failures/part-{run}-{writer}-{seq}.parquet   failed videos of the same part
    _index/part-{run}-{writer}-{seq}.parquet     one row per video of the part: its id,
                                                 settings digest, status, rows, run
    _corpus.json                                 the layout's version
    summary.json                                 the last run's counts (``state``: running,
                                                 finished, interrupted or failed)
    _staging/                                    local files being written (renamed into
                                                 place when whole)

A part is the work of one actor (``writer``: one per actor start) between two flushes.
It is published in this order: its tracks, its failures, each read back (row count and
schema version from the footer), then its index. The index is the commit: a video is
done or failed once an index names it, and a rerun reads only the indexes. A part
without an index (its actor died while writing it) is an orphan and is removed when no
actor runs (before and after every run, and for a dead actor's own parts at once).

``run`` is a UTC time to the microsecond, so later runs sort later. When a video has
been tracked again (``--overwrite``, ``--retry-failed``, other settings), its older
entries are superseded: the latest done result is kept, and the latest failure if it is
newer than that; `compact` rewrites or removes the parts holding superseded rows once
the run's actors have stopped.
"""

from __future__ import annotations

import datetime
import json
import re
import uuid
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from taptr.corpus.index_check import IndexPart, read_index_part
from taptr.corpus.schema import (
    SCHEMA_KEY,
    SCHEMA_VERSION,
    failures_schema,
    index_schema,
    tracks_schema,
)
from taptr.corpus.storage import STAGING, Storage, StoreError

if TYPE_CHECKING:
    import pyarrow as pa

LAYOUT_VERSION = 2
"""Version of the folder's layout, in ``_corpus.json``."""

TRACKS, FAILURES, INDEX = "tracks", "failures", "_index"
"""The folders of the tables and of the parts' index."""

SUMMARY, MARKER = "summary.json", "_corpus.json"
"""The run's summary and the layout's marker."""

PART = re.compile(r"^part-(?P<run>\d{8}T\d{12}Z)-(?P<writer>[0-9a-f]{8})-(?P<seq>\d{6})$")
"""A part's name: run, writer (one per actor start) and the writer's count of parts."""

OLD_LAYOUT_FILE = re.compile(r"^[A-Za-z0-9_-]*-[0-9a-f]{16}\.[0-9a-f]{16}\.parquet$")
"""A file of layout 1 (``{key}.{digest}.parquet``, one per video)."""

FOOTER_READERS = 8
"""Part footers read at once when a run checks the parts it will trust."""

MAX_MARKER_BYTES = 4096
"""Largest ``_corpus.json`` read: it holds a few numbers."""


def new_run() -> str:
    """A run's id: the UTC time to the microsecond (``20261207T013309123456Z``)."""
    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%S%fZ")


def new_writer() -> str:
    """A writer's id: 8 hex digits, unique to one actor start."""
    return uuid.uuid4().hex[:8]


def part_name(run: str, writer: str, seq: int) -> str:
    """The name of a writer's ``seq``-th part of a run."""
    return f"part-{run}-{writer}-{seq:06d}"


@dataclass(frozen=True)
class ResultLayout:
    """A corpus's output folder (see the module docstring).

    Attributes:
        storage: where it is (a local folder or a URI).
    """

    storage: Storage

    @classmethod
    def at(cls, out: str) -> ResultLayout:
        """The layout of ``out`` (a local path or a URI)."""
        return cls(Storage(out))

    def file(self, folder: str, part: str) -> str:
        """The path of a part's file in ``folder`` (relative to OUT).

        Raises:
            ValueError: ``part`` is not a name the layout makes (`PART`): whatever a file
                says, no other path is ever opened, renamed or removed.
        """
        if folder not in (TRACKS, FAILURES, INDEX) or not PART.match(part):
            raise ValueError(f"{folder}/{part!r} is not a part of a corpus's layout")
        return f"{folder}/{part}.parquet"

    @property
    def tracks(self) -> str:
        """The tracks dataset: a path or URI that pandas, pyarrow, DuckDB and Ray read."""
        return self._shown(TRACKS)

    @property
    def failures(self) -> str:
        """The failure records, read the same ways."""
        return self._shown(FAILURES)

    def prepare(self) -> None:
        """Checks the folder (`check`), creates it and removes what a killed run left.

        Raises:
            ValueError: files that are not the job's own, links, or the old layout.
        """
        self.check()
        for folder in (TRACKS, FAILURES, INDEX):
            self.storage.make_folder(folder)
        marker = {"layout": LAYOUT_VERSION, "schema": SCHEMA_VERSION}
        self.storage.write(MARKER, (json.dumps(marker) + "\n").encode())
        self.finish()  # what a killed run left

    def check(self) -> None:
        """Refuses a folder holding anything the job did not write, before any work.

        Raises:
            ValueError: names the first few foreign files or links, or says how to move
                a folder of the old layout to this one.
        """
        foreign: list[str] = []
        old = 0
        for entry in self.storage.list(""):
            if entry.kind == "link":
                foreign.append(f"{entry.name} (a link)")
            elif entry.name in (TRACKS, FAILURES, INDEX) and entry.kind == "folder":
                found, stale = _foreign_parts(self.storage, entry.name)
                foreign += found
                old += stale
            elif entry.name == "_attempts" and entry.kind == "folder":
                old += 1
            elif not _own_top(entry.name, entry.kind, self.storage.local):
                foreign.append(entry.name + ("/" if entry.kind == "folder" else ""))
        if old:
            raise ValueError(
                f"{self.storage.out} holds results of the old layout (one file per video): "
                "move them to this layout first with --migrate (docs/CORPUS.md, Migrating)"
            )
        if foreign:
            listed = ", ".join(foreign[:5]) + (
                f" and {len(foreign) - 5} more" if foreign[5:] else ""
            )
            raise ValueError(
                f"{self.storage.out} holds files that are not this job's own: {listed}; "
                "give --out a folder of its own (or remove them)"
            )
        self._check_marker()

    def publish(self, folder: str, part: str, table: pa.Table) -> None:
        """Writes a part's table whole, then reads its footer back.

        Raises:
            OSError: the file read back does not hold the rows written.
            StoreError: the store did not answer.
        """
        import pyarrow as pa
        import pyarrow.parquet as pq

        sink = pa.BufferOutputStream()
        pq.write_table(table, sink)
        relative = self.file(folder, part)
        self.storage.write(relative, sink.getvalue())
        path = self.storage.path(relative)
        try:
            footer = self.storage.footer(relative)
        except StoreError:
            raise
        except (ValueError, FileNotFoundError) as error:  # ArrowInvalid: no readable footer
            self.storage.delete(relative)  # readers of the dataset must not meet it
            raise OSError(f"{path} does not read back: {' '.join(str(error).split())}") from None
        version = (footer.metadata or {}).get(SCHEMA_KEY)
        if footer.num_rows != table.num_rows or version != SCHEMA_VERSION.encode():
            self.storage.delete(relative)
            raise OSError(
                f"{path} read back with {footer.num_rows} rows (schema {version!r}) where "
                f"{table.num_rows} were written: the store lost or changed them"
            )

    def read_index(self, parts: Iterable[str] | None = None) -> pa.Table:
        """The entries of every sound index file (or of ``parts``) as one table.

        Damaged files (`taptr.corpus.index_check`) are left out, not removed: a run's
        start removes them (`taptr.corpus.damage.sound_index`).
        """
        import pyarrow as pa

        found = [part.entries for part in self.index_parts(parts) if part.entries is not None]
        return pa.concat_tables(found) if found else index_schema().empty_table()

    def index_parts(self, parts: Iterable[str] | None = None) -> list[IndexPart]:
        """Every index file (or those of ``parts``) read and checked, a few at a time.

        An object store answers each read in milliseconds; thousands of parts are read
        `FOOTER_READERS` at once.
        """
        from concurrent.futures import ThreadPoolExecutor

        names = self.parts(INDEX) if parts is None else list(parts)

        def read(part: str) -> IndexPart:
            return read_index_part(self.storage, self.file(INDEX, part), part)

        with ThreadPoolExecutor(FOOTER_READERS) as pool:
            return list(pool.map(read, names))

    def parts(self, folder: str, writer: str | None = None) -> list[str]:
        """The names of the parts in ``folder`` (of one ``writer``), sorted."""
        names = []
        for entry in self.storage.list(folder):
            match = PART.match(entry.name.removesuffix(".parquet"))
            if match and (writer is None or match["writer"] == writer):
                names.append(match.string)
        return sorted(names)

    def remove_orphans(self, writer: str | None = None) -> list[str]:
        """Removes the parts (of ``writer``) that no index names; returns their names.

        Only when their writer cannot be writing them: no actor runs, or it is dead.
        """
        indexed = set(self.parts(INDEX, writer))
        orphans = []
        for folder in (TRACKS, FAILURES):
            for part in self.parts(folder, writer):
                if part not in indexed:
                    self.storage.delete(self.file(folder, part))
                    orphans.append(part)
        return orphans

    def remove_unnamed(self, entries: pa.Table) -> list[str]:
        """Removes the tracks and failures files no entry names; returns them (relative).

        A file whose index is gone or damaged, or whose index has no entry of its kind
        (a planted or left-over file), would otherwise be read with the dataset. Only
        when no actor is writing.

        Args:
            entries: the sound index entries (`taptr.corpus.damage.sound_index`).
        """
        from taptr.corpus.records import DONE

        named: dict[str, set[str]] = {TRACKS: set(), FAILURES: set()}
        kinds = entries.select(["part", "status"]).group_by(["part", "status"]).aggregate([])
        pairs = zip(kinds["part"].to_pylist(), kinds["status"].to_pylist(), strict=True)
        for part, status in pairs:
            named[TRACKS if status == DONE else FAILURES].add(part)
        removed = []
        for folder in (TRACKS, FAILURES):
            for part in self.parts(folder):
                if part not in named[folder]:
                    self.storage.delete(self.file(folder, part))
                    removed.append(self.file(folder, part))
        return removed

    def finish(self) -> None:
        """Removes orphan parts and staged files (no actor is writing any more)."""
        self.remove_orphans()
        if self.storage.local:
            for entry in self.storage.list(STAGING):
                self.storage.delete(f"{STAGING}/{entry.name}")

    def remove_part(self, part: str) -> None:
        """Removes a part: its index first, so that no moment names missing rows."""
        for folder in (INDEX, TRACKS, FAILURES):
            self.storage.delete(self.file(folder, part))

    def write_summary(self, summary: dict[str, Any]) -> None:
        """Writes ``summary.json`` whole."""
        self.storage.write(SUMMARY, (json.dumps(summary, indent=2) + "\n").encode())

    def read_tracks(self) -> pa.Table:
        """The tracks dataset as one table."""
        return self._read(TRACKS, tracks_schema())

    def read_failures(self) -> pa.Table:
        """The failure records as one table."""
        return self._read(FAILURES, failures_schema())

    def _read(self, folder: str, schema: pa.Schema) -> pa.Table:
        import pyarrow.dataset as ds

        files = [self.storage.path(self.file(folder, part)) for part in self.parts(folder)]
        if not files:  # nothing written (no failure at all): the columns all the same
            return schema.empty_table()
        with self.storage.answering():
            fs = self.storage.fs
            return ds.dataset(files, schema=schema, format="parquet", filesystem=fs).to_table()

    def _shown(self, folder: str) -> str:
        out = self.storage.out.rstrip("/")
        if "?" in out:  # a URI's parameters stay at its end
            base, _, query = out.partition("?")
            return f"{base}/{folder}?{query}"
        return f"{out}/{folder}"

    def _check_marker(self) -> None:
        if not self.storage.exists(MARKER):
            return
        try:
            marker = json.loads(self.storage.read(MARKER, MAX_MARKER_BYTES))
            version = marker["layout"]
        except StoreError:
            raise
        except (ValueError, KeyError, TypeError, RecursionError):  # JSONDecodeError, too big
            version = None
        if type(version) is not int:  # 1e999, "2", true, null: not what taptr writes
            raise ValueError(f"{self.storage.path(MARKER)} is not a taptr corpus marker")
        if version > LAYOUT_VERSION:
            raise ValueError(
                f"{self.storage.out} was written by a newer taptr (layout {version}; this "
                f"one writes {LAYOUT_VERSION}): upgrade taptr to add to it"
            )


def _own_top(name: str, kind: str, local: bool) -> bool:
    """Whether a name at the top of OUT is the job's own."""
    if kind == "file":
        return name in (SUMMARY, MARKER)
    return kind == "folder" and local and name == STAGING


def _foreign_parts(storage: Storage, folder: str) -> tuple[list[str], int]:
    """(foreign names, files of the old layout) in one of the job's folders."""
    foreign, old = [], 0
    for entry in storage.list(folder):
        stem = entry.name.removesuffix(".parquet")
        if entry.kind == "file" and entry.name.endswith(".parquet") and PART.match(stem):
            continue
        if entry.kind == "file" and folder != INDEX and OLD_LAYOUT_FILE.match(entry.name):
            old += 1
            continue
        suffix = " (a link)" if entry.kind == "link" else "/" if entry.kind == "folder" else ""
        foreign.append(f"{folder}/{entry.name}{suffix}")
    return foreign, old
