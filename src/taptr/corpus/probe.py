"""The CPU task of a corpus: read a video's header, check it, build its queries.

Runs as a Ray Data ``map`` task before a tracker actor sees the video, so that a corrupt
file, one without frames, one larger than allowed or queries that do not fit it are found
on a CPU, without holding a GPU actor, and recorded as failed (``error`` set) while the
rest go on.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from taptr.corpus.inputs import QuerySpec, build_queries


def probe_video(row: dict[str, Any], max_video_frames: int | None) -> dict[str, Any]:
    """Adds the header and queries to a video's row, or the one-line reason it cannot run.

    Args:
        row: ``video_id``, ``path``, ``queries`` (`QuerySpec` JSON), ``digest``, ``key``.
        max_video_frames: refuse videos that declare more frames (None: no limit).

    Returns:
        The row with ``num_frames`` (declared; 0 when unknown), ``height``, ``width``,
        ``fps`` (0.0 when unknown), ``query_array`` ((N, 3) float32 bytes) and ``error``
        ('' when the video can be tracked).
    """
    from taptr.io.video import video_info

    found: dict[str, Any] = {
        "num_frames": 0,
        "height": 0,
        "width": 0,
        "fps": 0.0,
        "query_array": b"",
        "error": "",
    }
    try:
        info = video_info(row["path"])
        if max_video_frames is not None and (info.num_frames or 0) > max_video_frames:
            raise ValueError(
                f"declares {info.num_frames} frames, more than the limit of {max_video_frames}"
            )
        found.update(
            num_frames=info.num_frames or 0,
            height=info.height,
            width=info.width,
            fps=float(info.fps or 0.0),
        )
        spec = QuerySpec.from_json(row["queries"])
        length = info.num_frames or 1 << 30  # unknown: checked on the decoded frames
        queries = build_queries(spec, length, info.height, info.width)
        found["query_array"] = np.ascontiguousarray(queries, np.float32).tobytes()
    except Exception as error:  # every reason a video cannot be tracked is a failure row
        found["error"] = one_line(error)
    return {**row, **found}


def one_line(error: BaseException) -> str:
    """An exception as one line: its message, or its type when it has none."""
    text = " ".join(str(error).split())
    if isinstance(error, (ValueError, FileNotFoundError, OSError)) and text:
        return text
    return f"{type(error).__name__}: {text}" if text else type(error).__name__
