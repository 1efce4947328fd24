"""What the index says of each video: its standing result and failure.

A video tracked more than once (``--overwrite``, ``--retry-failed``, other settings) has
several index entries. Its standing ones: the latest done entry (its result), and the
latest failure when that is newer than the result (the result stays valid for its
settings; the failure says the latest try failed). Entries are ordered by run, then part
name (`taptr.corpus.layout`). A rerun skips a video whose standing result, or failure,
has its digest; compaction (`taptr.corpus.compaction`) drops every other entry's rows.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from taptr.corpus.records import DONE, FAILED

if TYPE_CHECKING:
    import pyarrow as pa


@dataclass(frozen=True)
class Entry:
    """One index entry.

    Attributes:
        order: ``{run}|{part}``: later entries sort later.
        digest: its settings digest; part: the part holding its rows.
    """

    order: str
    digest: str
    part: str


def standing(index: pa.Table) -> dict[str, tuple[Entry | None, Entry | None]]:
    """Per video id: (its standing result, its standing failure), None where there is none.

    Args:
        index: index rows (`taptr.corpus.schema.index_schema`).
    """
    latest: dict[tuple[str, str], Entry] = {}
    columns = ("video_id", "status", "run", "part", "settings_digest")
    values = (index[name].to_pylist() for name in columns)
    for video_id, status, run, part, digest in zip(*values, strict=True):
        order = f"{run}|{part}"
        known = latest.get((video_id, status))
        if known is None or order > known.order:
            latest[(video_id, status)] = Entry(order, digest, part)
    found: dict[str, tuple[Entry | None, Entry | None]] = {}
    for video_id, _ in latest:
        done, failed = latest.get((video_id, DONE)), latest.get((video_id, FAILED))
        if failed is not None and done is not None and failed.order <= done.order:
            failed = None
        found[video_id] = (done, failed)
    return found
