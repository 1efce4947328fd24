"""A corpus's results read back as tables, with their columns even when a folder is empty.

``pd.read_parquet("OUT/failures")`` fails when nothing failed: an object store has no
folder without files (``FileNotFoundError``), a local empty folder reads as a table
without columns. These read ``OUT`` (a folder or a URI, as given to the job) through the
layout: every column of the schema (`taptr.corpus.schema`), zero rows when there are none.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from taptr.corpus.layout import ResultLayout

if TYPE_CHECKING:
    import pyarrow as pa


def read_tracks(out: str) -> pa.Table:
    """Every tracks row of the corpus in ``out`` (`taptr.corpus.schema.tracks_schema`).

    Raises:
        ValueError: ``out`` cannot be opened, or its store does not answer.
    """
    return ResultLayout.at(out).read_tracks()


def read_failures(out: str) -> pa.Table:
    """Every failure row of the corpus in ``out`` (`taptr.corpus.schema.failures_schema`).

    Raises:
        ValueError: ``out`` cannot be opened, or its store does not answer.
    """
    return ResultLayout.at(out).read_failures()
