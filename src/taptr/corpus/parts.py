"""An actor's (or the driver's) buffer of finished videos, published as parts.

Finished videos wait in memory as Arrow tables until the part is due: `PartLimits.videos`
videos, `PartLimits.megabytes` of rows, or `PartLimits.seconds` since its first video,
whichever comes first; the driver also asks an idle actor to flush. A part holds many
videos, so a corpus of 10⁶ videos is a few thousand files, not a million; the price of a
dead actor is the unflushed videos, tracked again (never written twice: the driver reads
the dead writer's indexes first).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from taptr.corpus.layout import FAILURES, INDEX, TRACKS, ResultLayout, new_writer, part_name
from taptr.corpus.records import DONE, FAILED, Committed, Failure, VideoTracks
from taptr.corpus.schema import failures_table, index_schema, tracks_table

if TYPE_CHECKING:
    import pyarrow as pa


@dataclass(frozen=True)
class PartLimits:
    """When a part is due (whichever comes first).

    Attributes:
        videos: videos in the part.
        megabytes: MiB of rows in memory (Arrow) before writing.
        seconds: seconds since the part's first video (bounds what a dead actor loses).
    """

    videos: int = 1000
    megabytes: float = 128.0
    seconds: float = 120.0


@dataclass
class PartWriter:
    """Gathers finished videos and publishes them as parts of ``layout``.

    Attributes:
        layout: the output folder.
        run: the run's id.
        limits: when a part is due.
        writer: this writer's id (in every part's name).
    """

    layout: ResultLayout
    run: str
    limits: PartLimits = field(default_factory=PartLimits)
    writer: str = field(default_factory=new_writer)
    _seq: int = 0
    _tracks: list[pa.Table] = field(default_factory=list)
    _failures: list[Failure] = field(default_factory=list)
    _entries: list[tuple[int, str, str, str, int]] = field(default_factory=list)
    _bytes: int = 0
    _opened: float | None = None

    def add_tracks(self, index: int, video: VideoTracks) -> None:
        """Holds a tracked video's rows for the next part."""
        table = tracks_table(video)
        self._tracks.append(table)
        self._bytes += table.nbytes
        self._add(index, video.video_id, video.digest, DONE, table.num_rows)

    def add_failure(self, index: int, failure: Failure) -> None:
        """Holds a failed video's record for the next part."""
        self._failures.append(failure)
        self._bytes += len(failure.error) + len(failure.path) + len(failure.video_id)
        self._add(index, failure.video_id, failure.digest, FAILED, 1)

    @property
    def pending(self) -> int:
        """Videos waiting for a part."""
        return len(self._entries)

    def due(self) -> bool:
        """Whether the part should be written now."""
        if not self._entries:
            return False
        limits = self.limits
        return (
            len(self._entries) >= limits.videos
            or self._bytes >= limits.megabytes * 2**20
            or time.monotonic() - (self._opened or 0.0) >= limits.seconds
        )

    def flush(self) -> Committed | None:
        """Publishes the waiting videos as one part (None when there are none)."""
        import pyarrow as pa

        if not self._entries:
            return None
        part = part_name(self.run, self.writer, self._seq)
        self._seq += 1
        if self._tracks:
            self.layout.publish(TRACKS, part, pa.concat_tables(self._tracks))
        if self._failures:
            self.layout.publish(FAILURES, part, failures_table(self._failures))
        self.layout.publish(INDEX, part, self._index(part))
        committed = Committed(part, tuple(entry[0] for entry in self._entries))
        self._tracks, self._failures, self._entries = [], [], []
        self._bytes, self._opened = 0, None
        return committed

    def _add(self, index: int, video_id: str, digest: str, status: str, rows: int) -> None:
        if self._opened is None:
            self._opened = time.monotonic()
        self._entries.append((index, video_id, digest, status, rows))

    def _index(self, part: str) -> pa.Table:
        import pyarrow as pa

        entries = self._entries
        columns = {
            "video_id": [entry[1] for entry in entries],
            "settings_digest": [entry[2] for entry in entries],
            "status": [entry[3] for entry in entries],
            "rows": [entry[4] for entry in entries],
            "run": [self.run] * len(entries),
            "part": [part] * len(entries),
        }
        return pa.Table.from_pydict(columns, schema=index_schema())
