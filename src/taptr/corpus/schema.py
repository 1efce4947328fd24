"""The columns of a corpus's tables: tracks, failures and the parts' index.

docs/CORPUS.md describes each column. Version 2 added ``declared_frames`` and
``decoded_frames`` to both tables (version 1, one file per video, had neither; see
`taptr.corpus.migrate`). Every file carries its version in its metadata (``taptr.schema``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from taptr.corpus.records import Failure, VideoTracks

if TYPE_CHECKING:
    import pyarrow as pa

SCHEMA_VERSION = "2"
"""Version of the tables' columns, in every file's metadata as ``taptr.schema``."""

SCHEMA_KEY = b"taptr.schema"
"""The metadata key of the version."""


def tracks_schema() -> pa.Schema:
    """One row per video and query point."""
    import pyarrow as pa

    return pa.schema(
        [
            ("video_id", pa.string()),
            ("path", pa.string()),
            ("point_id", pa.int32()),
            ("query", pa.list_(pa.float32(), 3)),  # (t, x, y) pixels
            ("positions", pa.list_(pa.list_(pa.float32(), 2))),  # T × (x, y) pixels
            ("visibility", pa.list_(pa.bool_())),  # T
            ("num_frames", pa.int32()),
            ("declared_frames", pa.int32()),  # null: the container does not say
            ("decoded_frames", pa.int32()),
            ("height", pa.int32()),
            ("width", pa.int32()),
            ("fps", pa.float64()),
            ("model", pa.string()),
            ("settings_digest", pa.string()),
        ],
        metadata={SCHEMA_KEY: SCHEMA_VERSION},
    )


def failures_schema() -> pa.Schema:
    """One row per failed video."""
    import pyarrow as pa

    return pa.schema(
        [
            ("video_id", pa.string()),
            ("path", pa.string()),
            ("error", pa.string()),
            ("attempts", pa.int32()),
            ("declared_frames", pa.int32()),
            ("decoded_frames", pa.int32()),
            ("settings_digest", pa.string()),
        ],
        metadata={SCHEMA_KEY: SCHEMA_VERSION},
    )


def index_schema() -> pa.Schema:
    """One row per video of a part: what a rerun reads instead of the parts themselves."""
    import pyarrow as pa

    return pa.schema(
        [
            ("video_id", pa.string()),
            ("settings_digest", pa.string()),
            ("status", pa.string()),  # done or failed
            ("rows", pa.int32()),  # rows of the video in the part
            ("run", pa.string()),  # the run that tracked it (later runs supersede)
            ("part", pa.string()),  # the part holding its rows
        ],
        metadata={SCHEMA_KEY: SCHEMA_VERSION},
    )


def tracks_table(video: VideoTracks) -> pa.Table:
    """A video's rows, the arrays built from numpy without Python lists."""
    import pyarrow as pa

    num_frames, num_points = video.visibility.shape
    height, width = video.size
    # row n holds point n's whole track: (N, T, 2) positions, (N, T) visibility
    positions = np.ascontiguousarray(video.tracks.transpose(1, 0, 2), np.float32).reshape(-1)
    visibility = np.ascontiguousarray(video.visibility.T).reshape(-1)
    offsets = pa.array(np.arange(num_points + 1, dtype=np.int32) * num_frames)
    queries = np.ascontiguousarray(video.queries, np.float32).reshape(-1)
    pairs = pa.FixedSizeListArray.from_arrays(pa.array(positions), 2)

    def repeated(value: object) -> list:
        return [value] * num_points

    columns: dict[str, Any] = {
        "video_id": repeated(video.video_id),
        "path": repeated(video.path),
        "point_id": pa.array(np.arange(num_points, dtype=np.int32)),
        "query": pa.FixedSizeListArray.from_arrays(pa.array(queries), 3),
        "positions": pa.ListArray.from_arrays(offsets, pairs),
        "visibility": pa.ListArray.from_arrays(offsets, pa.array(visibility)),
        "num_frames": repeated(num_frames),
        "declared_frames": repeated(video.declared_frames),
        "decoded_frames": repeated(num_frames),
        "height": repeated(height),
        "width": repeated(width),
        "fps": repeated(video.fps),
        "model": repeated(video.model),
        "settings_digest": repeated(video.digest),
    }
    return pa.Table.from_pydict(columns, schema=tracks_schema())


def failures_table(failures: list[Failure]) -> pa.Table:
    """The rows of failed videos."""
    import pyarrow as pa

    columns = {
        "video_id": [f.video_id for f in failures],
        "path": [f.path for f in failures],
        "error": [f.error for f in failures],
        "attempts": [f.attempts for f in failures],
        "declared_frames": [f.declared_frames for f in failures],
        "decoded_frames": [f.decoded_frames for f in failures],
        "settings_digest": [f.digest for f in failures],
    }
    return pa.Table.from_pydict(columns, schema=failures_schema())
