"""What the index says of each video: its standing result and failure.

A video tracked more than once (``--overwrite``, ``--retry-failed``, other settings) has
several index entries. Its standing ones: the latest done entry (its result), and the
latest failure when that is newer than the result (the result stays valid for its
settings; the failure says the latest try failed). Entries are ordered by run, then part
name (`taptr.corpus.layout`). A rerun skips a video whose standing result, or failure,
has its digest; compaction (`taptr.corpus.compaction`) drops every other entry's rows.

Everything stays in Arrow: at 10⁶ videos a Python object per entry would cost the driver
hundreds of megabytes.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from taptr.corpus.records import DONE, FAILED

if TYPE_CHECKING:
    import pyarrow as pa

STANDING_COLUMNS = ("video_id", "done_digest", "done_part", "failed_digest", "failed_part")
"""Columns of `standing`: per video, its standing result's and failure's digest and part."""


def standing(index: pa.Table) -> pa.Table:
    """One row per video id of ``index``: `STANDING_COLUMNS`, null where there is none.

    Args:
        index: index rows (`taptr.corpus.schema.index_schema`).
    """
    import pyarrow as pa
    import pyarrow.compute as pc

    order = pc.binary_join_element_wise(index["run"], index["part"], "|")
    entries = index.select(["video_id", "status", "settings_digest", "part"]).append_column(
        "order", order
    )
    latest = entries.group_by(["video_id", "status"]).aggregate([("order", "max")])
    latest = latest.rename_columns(["video_id", "status", "order"])
    latest = latest.join(entries, keys=["video_id", "status", "order"])
    done, failed = (_of_status(latest, status) for status in (DONE, FAILED))
    both = done.join(failed, keys="video_id", join_type="full outer")
    # a failure stands beside a result only when it is newer
    newer = pc.fill_null(pc.greater(both["failed_order"], both["done_order"]), True)
    found = {"video_id": both["video_id"]}
    for name in ("done_digest", "done_part"):
        found[name] = both[name]
    for name in ("failed_digest", "failed_part"):
        nothing = pa.nulls(len(both), pa.string())
        found[name] = pc.if_else(newer, both[name], nothing)
    return pa.table(found)


def _of_status(latest: pa.Table, status: str) -> pa.Table:
    """The latest entries of one status, their columns prefixed with it."""
    import pyarrow.compute as pc

    rows = latest.filter(pc.equal(latest["status"], status))
    prefix = "done" if status == DONE else "failed"
    rows = rows.select(["video_id", "order", "settings_digest", "part"])
    return rows.rename_columns(
        ["video_id", f"{prefix}_order", f"{prefix}_digest", f"{prefix}_part"]
    )
