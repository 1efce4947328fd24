"""A video's header and queries, checked before its frames reach the model.

The actor reads each video's header and first frame before it announces the video as
started: a missing, corrupt or oversized file, or queries that do not fit it, is a failure
row with no tracking attempt (a header takes milliseconds to read).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from taptr.corpus.inputs import QuerySpec, build_queries
from taptr.corpus.records import VideoTask
from taptr.io.video import VideoInfo, video_info


@dataclass(frozen=True)
class Probed:
    """What a video's header says, and its queries.

    Attributes:
        info: frame count (declared; None when unknown), rate and size.
        queries: (N, 3) float32 (t, x, y) pixel queries.
    """

    info: VideoInfo
    queries: np.ndarray


class ProbeError(ValueError):
    """A video whose header was read but cannot be tracked.

    Attributes:
        declared_frames: frames its container declares (None: it does not say).
    """

    def __init__(self, message: str, declared_frames: int | None) -> None:
        super().__init__(message)
        self.declared_frames = declared_frames


def probe_video(task: VideoTask, max_video_frames: int | None) -> Probed:
    """Reads a video's header and builds its queries.

    Args:
        task: the video.
        max_video_frames: refuse videos that declare more frames (None: no limit).

    Raises:
        FileNotFoundError, ValueError: the video cannot be read (one line naming why).
        ProbeError: its header was read, but it or its queries cannot be tracked.
    """
    info = video_info(task.path)
    try:
        if max_video_frames is not None and (info.num_frames or 0) > max_video_frames:
            raise ValueError(
                f"declares {info.num_frames} frames, more than the limit of {max_video_frames}"
            )
        spec = QuerySpec.from_json(task.queries)
        length = info.num_frames or 1 << 30  # unknown: checked on the decoded frames
        queries = build_queries(spec, length, info.height, info.width)
    except ValueError as error:
        raise ProbeError(str(error), info.num_frames) from None
    return Probed(info, np.ascontiguousarray(queries, np.float32))
