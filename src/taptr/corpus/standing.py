"""What the index says of each video: its standing result and failure.

A video tracked more than once (``--overwrite``, ``--retry-failed``, other settings) has
several index entries. Its standing ones: the latest done entry (its result), and the
latest failure when that is newer than the result (the result stays valid for its
settings; the failure says the latest try failed). Entries are ordered by run, then part
name (`taptr.corpus.layout`). A rerun skips a video whose standing result, or failure,
has its digest; compaction (`taptr.corpus.compaction`) drops every other entry's rows.

One sort of the index by (video, run, part) puts each video's entries together in time
order; the rest is numpy over positions in that order. No Python object per entry, and
no hash join: at 10⁶ videos Arrow's group-by and joins held about 1 GB more of the
driver's memory than this (docs/BENCHMARKS.md, "A corpus at scale").
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from taptr.corpus.records import DONE, FAILED

if TYPE_CHECKING:
    import pyarrow as pa

STANDING_COLUMNS = ("video_id", "done_digest", "done_part", "failed_digest", "failed_part")
"""Columns of `standing`: per video, its standing result's and failure's digest and part."""


def standing(index: pa.Table) -> pa.Table:
    """One row per video id of ``index``, sorted by id: `STANDING_COLUMNS`, null where none.

    Args:
        index: index rows (`taptr.corpus.schema.index_schema`).
    """
    import pyarrow as pa
    import pyarrow.compute as pc

    if len(index) == 0:
        return pa.table({name: pa.array([], pa.string()) for name in STANDING_COLUMNS})
    keys = [("video_id", "ascending"), ("run", "ascending"), ("part", "ascending")]
    order = pc.sort_indices(index.select(["video_id", "run", "part"]), sort_keys=keys)
    ids = index["video_id"].take(order)
    status = index["status"].take(order)
    # group g holds one video's entries, oldest first: (E,) group of each sorted entry
    starts = np.concatenate([[True], _differs(ids)])
    group = np.cumsum(starts) - 1
    done = _latest(group, pc.equal(status, DONE).to_numpy(zero_copy_only=False))
    failed = _latest(group, pc.equal(status, FAILED).to_numpy(zero_copy_only=False))
    # a failure stands beside a result only when it is newer (later in the group)
    failed[failed < done] = -1
    found = {"video_id": ids.filter(pa.array(starts))}
    for prefix, latest in (("done", done), ("failed", failed)):
        entries = pa.array(order.to_numpy()[np.maximum(latest, 0)], mask=latest < 0)
        found[f"{prefix}_digest"] = index["settings_digest"].take(entries)
        found[f"{prefix}_part"] = index["part"].take(entries)
    return pa.table(found)


def _differs(ids: pa.ChunkedArray | pa.Array) -> np.ndarray:
    """(E − 1,) whether each sorted id but the first differs from the one before it."""
    import pyarrow.compute as pc

    return pc.not_equal(ids[1:], ids[:-1]).to_numpy(zero_copy_only=False)


def _latest(group: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """(G,) per group, the sorted position of its last chosen entry, −1 where none."""
    latest = np.full(int(group[-1]) + 1, -1, np.int64)
    positions = np.flatnonzero(chosen)
    if len(positions) == 0:
        return latest
    # positions ascend, so within a group the last one written is the latest
    last = np.concatenate([group[positions[1:]] != group[positions[:-1]], [True]])
    latest[group[positions[last]]] = positions[last]
    return latest
