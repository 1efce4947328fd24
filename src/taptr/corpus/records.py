"""What travels between the driver and the tracker actors of a corpus: typed records.

The driver hands an actor a list of `VideoTask`; the actor streams back lists of events in
the order they happen: `Started` just before it starts tracking a video (so that a death
is charged to the video it was tracking, and to no other), `Finished` once a video is
tracked or found impossible (not yet written), `Committed` once a part holding finished
videos is published and read back. A video counts as done or failed only when committed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DONE = "done"
"""Status of a video whose rows are written."""

FAILED = "failed"
"""Status of a video recorded as failed."""


@dataclass(frozen=True, slots=True)
class VideoTask:
    """One video, as the driver hands it to an actor.

    Attributes:
        index: the video's place in the run's plan (how events name it).
        video_id: its id in the results; path: its file or image folder.
        queries: its `taptr.corpus.inputs.QuerySpec` as JSON.
        digest: the settings digest its result is made with.
        attempt: the tracking attempt this is (1 for the first; more after workers died).
    """

    index: int
    video_id: str
    path: str
    queries: str
    digest: str
    attempt: int = 1


@dataclass(frozen=True, slots=True)
class Started:
    """An actor starts tracking the video ``index`` (its header and queries are fine)."""

    index: int


@dataclass(frozen=True, slots=True)
class Finished:
    """An actor is done with a video; its rows or failure wait in the actor's next part.

    Attributes:
        index: the video.
        status: `DONE` or `FAILED`; error: the one-line reason of a failure.
        frames: frames tracked; points: query points (0 for a failure).
        seconds: the actor's time on it (reading, tracking).
    """

    index: int
    status: str
    error: str = ""
    frames: int = 0
    points: int = 0
    seconds: float = 0.0


@dataclass(frozen=True)
class Committed:
    """A part is published and read back: its videos are done or failed for good.

    Attributes:
        part: the part's name (`taptr.corpus.layout`); indices: its videos.
    """

    part: str
    indices: tuple[int, ...]


Event = Started | Finished | Committed
"""What an actor reports."""


@dataclass(frozen=True)
class VideoTracks:
    """One tracked video, ready to be written.

    Attributes:
        video_id: the video's id; path: its file.
        queries: (N, 3) float32 (t, x, y) pixel queries.
        tracks: (T, N, 2) float32 (x, y) pixels, pixel centres at integers.
        visibility: (T, N) bool.
        size: (height, width) of the frames; fps: frames per second (None: unknown).
        declared_frames: frames the container declares (None: it does not say).
        model: the model's name or file; digest: the settings digest.
    """

    video_id: str
    path: str
    queries: np.ndarray
    tracks: np.ndarray
    visibility: np.ndarray
    size: tuple[int, int]
    fps: float | None
    declared_frames: int | None
    model: str
    digest: str


@dataclass(frozen=True)
class Failure:
    """One video that could not be tracked.

    Attributes:
        video_id: the video's id; path: its file.
        error: why, in one line.
        attempts: tracking attempts started (0: it never reached a tracker's model).
        declared_frames: frames its container declares (None: unknown or unread).
        decoded_frames: frames decoded before it failed (None: not known).
        digest: the settings digest it failed with.
    """

    video_id: str
    path: str
    error: str
    attempts: int
    declared_frames: int | None
    decoded_frames: int | None
    digest: str
