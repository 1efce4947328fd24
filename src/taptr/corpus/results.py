"""The results of a corpus: a Parquet dataset of tracks, failure records, attempt markers.

Layout of ``OUT``:

- ``tracks/{key}.{digest}.parquet``: one file per video, one row per query point
  (`TRACKS_SCHEMA`); ``key`` is `taptr.corpus.inputs.video_key` of the video id and
  ``digest`` the settings digest. Read the folder as one dataset with pandas, pyarrow,
  DuckDB or Ray.
- ``failures/{key}.{digest}.parquet``: one row per failed video (`FAILURES_SCHEMA`).
- ``_attempts/{key}.{digest}/``: one empty file per started attempt; counts the tries of
  a video whose worker died, across worker restarts (cleared when a run starts).
- ``_staging/``: files being written; each is renamed into place when complete, so a
  video's result appears whole or not at all (same filesystem, so the rename is atomic).
- ``summary.json``: the last run's counts and speeds.

A video's new result replaces its results made with other settings (removed after the new
file is in place; for that moment both are there, told apart by ``settings_digest``), and
removes its failure records.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import pyarrow as pa

SCHEMA_VERSION = "1"
"""Version of the tracks schema, stored in every file's metadata (``taptr.schema``)."""


def tracks_schema() -> pa.Schema:
    """Columns of the tracks dataset (docs/CORPUS.md describes each)."""
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
            ("height", pa.int32()),
            ("width", pa.int32()),
            ("fps", pa.float64()),
            ("model", pa.string()),
            ("settings_digest", pa.string()),
        ],
        metadata={"taptr.schema": SCHEMA_VERSION},
    )


def failures_schema() -> pa.Schema:
    """Columns of the failure records."""
    import pyarrow as pa

    return pa.schema(
        [
            ("video_id", pa.string()),
            ("path", pa.string()),
            ("error", pa.string()),
            ("attempts", pa.int32()),
            ("settings_digest", pa.string()),
        ],
        metadata={"taptr.schema": SCHEMA_VERSION},
    )


@dataclass(frozen=True)
class VideoTracks:
    """One tracked video, ready to be written.

    Attributes:
        video_id: the video's id; path: its file.
        queries: (N, 3) float32 (t, x, y) pixel queries.
        tracks: (T, N, 2) float32 (x, y) pixels, pixel centres at integers.
        visibility: (T, N) bool.
        size: (height, width) of the frames; fps: frames per second (None: unknown).
        model: the model's name or file; digest: the settings digest.
    """

    video_id: str
    path: str
    queries: np.ndarray
    tracks: np.ndarray
    visibility: np.ndarray
    size: tuple[int, int]
    fps: float | None
    model: str
    digest: str


@dataclass(frozen=True)
class ResultLayout:
    """Where a corpus's results live (see the module docstring).

    Attributes:
        root: the output folder (on a cluster, a filesystem every node mounts).
    """

    root: str

    @property
    def tracks(self) -> Path:
        """The Parquet dataset of tracks."""
        return Path(self.root) / "tracks"

    @property
    def failures(self) -> Path:
        """The failure records."""
        return Path(self.root) / "failures"

    def prepare(self) -> None:
        """Creates the folders and clears what an earlier run left half done."""
        for folder in (self.tracks, self.failures, self._staging):
            folder.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(self._staging, ignore_errors=True)
        shutil.rmtree(self._attempts, ignore_errors=True)
        self._staging.mkdir(exist_ok=True)

    def finish(self) -> None:
        """Removes the staging and attempt folders (every worker has stopped)."""
        shutil.rmtree(self._staging, ignore_errors=True)
        shutil.rmtree(self._attempts, ignore_errors=True)

    def done(self) -> set[str]:
        """File names in the tracks dataset (``{key}.{digest}.parquet``)."""
        with contextlib.suppress(FileNotFoundError):
            return {entry.name for entry in os.scandir(self.tracks)}
        return set()

    def failed(self) -> set[str]:
        """File names of the failure records."""
        with contextlib.suppress(FileNotFoundError):
            return {entry.name for entry in os.scandir(self.failures)}
        return set()

    def start_attempt(self, key: str, digest: str) -> int:
        """Records that an attempt at a video starts; returns the attempts before it."""
        folder = self._attempts / f"{key}.{digest}"
        folder.mkdir(parents=True, exist_ok=True)
        earlier = sum(1 for _ in os.scandir(folder))
        (folder / uuid.uuid4().hex).touch()
        return earlier

    def attempts(self, key: str, digest: str) -> int:
        """Attempts started at a video in this run."""
        with contextlib.suppress(FileNotFoundError):
            return sum(1 for _ in os.scandir(self._attempts / f"{key}.{digest}"))
        return 0

    def write_tracks(self, key: str, video: VideoTracks) -> Path:
        """Writes a video's rows atomically, then drops its other results and failures."""
        import pyarrow as pa

        table = pa.Table.from_pydict(_track_columns(video), schema=tracks_schema())
        name = f"{key}.{video.digest}.parquet"
        target = self._publish(table, self.tracks / name)
        self._remove(self.tracks, key, keep=name)
        self._remove(self.failures, key, keep=None)
        return target

    def write_failure(
        self, key: str, video_id: str, path: str, error: str, attempts: int, digest: str
    ) -> Path:
        """Records a failed video (its one-line error) atomically."""
        import pyarrow as pa

        row = {
            "video_id": [video_id],
            "path": [path],
            "error": [error],
            "attempts": [attempts],
            "settings_digest": [digest],
        }
        table = pa.Table.from_pydict(row, schema=failures_schema())
        name = f"{key}.{digest}.parquet"
        target = self._publish(table, self.failures / name)
        self._remove(self.failures, key, keep=name)
        return target

    def write_summary(self, summary: dict[str, Any]) -> None:
        """Writes ``summary.json`` atomically."""
        from taptr.io.atomic import atomic_path

        with atomic_path(Path(self.root) / "summary.json") as tmp:
            tmp.write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")

    @property
    def _staging(self) -> Path:
        return Path(self.root) / "_staging"

    @property
    def _attempts(self) -> Path:
        return Path(self.root) / "_attempts"

    def _publish(self, table: pa.Table, target: Path) -> Path:
        """Writes ``table`` under ``_staging`` and renames it onto ``target``."""
        import pyarrow.parquet as pq

        self._staging.mkdir(parents=True, exist_ok=True)
        staged = self._staging / f"{uuid.uuid4().hex}.parquet"
        try:
            pq.write_table(table, staged)
            os.replace(staged, target)
        finally:
            staged.unlink(missing_ok=True)
        return target

    @staticmethod
    def _remove(folder: Path, key: str, keep: str | None) -> None:
        """Removes ``folder``'s files of the video ``key`` but ``keep``."""
        for entry in folder.glob(f"{key}.*.parquet"):
            if entry.name != keep:
                entry.unlink(missing_ok=True)


def _track_columns(video: VideoTracks) -> dict[str, Any]:
    """Columns of a video's rows, the arrays built from numpy without Python lists."""
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

    return {
        "video_id": repeated(video.video_id),
        "path": repeated(video.path),
        "point_id": pa.array(np.arange(num_points, dtype=np.int32)),
        "query": pa.FixedSizeListArray.from_arrays(pa.array(queries), 3),
        "positions": pa.ListArray.from_arrays(offsets, pairs),
        "visibility": pa.ListArray.from_arrays(offsets, pa.array(visibility)),
        "num_frames": repeated(num_frames),
        "height": repeated(height),
        "width": repeated(width),
        "fps": repeated(video.fps),
        "model": repeated(video.model),
        "settings_digest": repeated(video.digest),
    }


def read_tracks(root: str | os.PathLike[str]) -> pa.Table:
    """The tracks dataset of a corpus output folder as one pyarrow table."""
    import pyarrow.parquet as pq

    return pq.read_table(Path(root) / "tracks", schema=tracks_schema())


def read_failures(root: str | os.PathLike[str]) -> pa.Table:
    """The failure records of a corpus output folder as one pyarrow table."""
    import pyarrow.parquet as pq

    return pq.read_table(Path(root) / "failures", schema=failures_schema())
