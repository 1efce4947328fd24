"""Whether a video decoded to the frames its container declares.

A file cut short (an interrupted download or copy) decodes to fewer frames than its
header states, and its tracks would silently cover only the start. ``taptr track`` and
``taptr track-corpus`` treat that as an error (a failure row in a corpus) unless asked to
keep the frames that decode; both counts are in the message and in the corpus's rows.
More frames than declared is a wrong header, not a cut file, and is no error.
"""

from __future__ import annotations

import os

ACCEPT_TRUNCATED = "--accept-truncated"
"""The option of ``taptr track`` and ``taptr track-corpus`` that keeps a short video's tracks."""


class TruncatedVideoError(ValueError):
    """A video decoded to fewer frames than its container declares: cut short or damaged.

    Attributes:
        decoded: frames decoded; declared: frames the container declares.
    """

    def __init__(self, path: str | os.PathLike[str], decoded: int, declared: int) -> None:
        super().__init__(
            f"{path}: decoded {decoded} of the {declared} frames its container declares (a "
            f"truncated or damaged file); {ACCEPT_TRUNCATED} keeps the tracks of the frames "
            "that decode"
        )
        self.decoded = decoded
        self.declared = declared


def check_decoded(
    path: str | os.PathLike[str],
    decoded: int,
    declared: int | None,
    max_frames: int | None = None,
    accept: bool = False,
) -> None:
    """Refuses a video that decoded to fewer frames than its container declares.

    Args:
        path: the video, for the message.
        decoded: frames decoded.
        declared: frames its container declares (None: it does not say; nothing to check).
        max_frames: frames asked for at most (a video cut there on purpose is not short).
        accept: keep a short video (``--accept-truncated``): no error.

    Raises:
        TruncatedVideoError: it is short and ``accept`` is False.
    """
    if not declared or accept:
        return
    expected = declared if max_frames is None else min(declared, max_frames)
    if decoded < expected:
        raise TruncatedVideoError(path, decoded, declared)
