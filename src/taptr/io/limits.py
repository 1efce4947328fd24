"""Named limits on the size of what taptr reads, each raisable by an environment variable.

Every reader checks what a file *declares* (a header, a length prefix, a frame count) against
these limits before it allocates memory for it, so a small crafted or damaged file cannot
make taptr ask for gigabytes. Values are read from the environment at each call, so a limit
can be raised for one run (``TAPTR_MAX_VIDEO_BYTES=16G taptr track ...``) or from Python
(``os.environ[...]`` before the call).

======================  =============================  ==========  ===============================
name                    environment variable           default     what it bounds
======================  =============================  ==========  ===============================
``file_bytes``          ``TAPTR_MAX_FILE_BYTES``       8 GiB       one dataset file (TAP-Vid
                                                                   pickle, Kubric ``.npy``)
``checkpoint_bytes``    ``TAPTR_MAX_CHECKPOINT_BYTES`` 4 GiB       a checkpoint file, and the
                                                                   total bytes of its tensors
``video_bytes``         ``TAPTR_MAX_VIDEO_BYTES``      4 GiB       one video's decoded frames
                                                                   (T × H × W × 3 bytes)
``video_frames``        ``TAPTR_MAX_VIDEO_FRAMES``     10,000      frames of one TAP-Vid video
``image_pixels``        ``TAPTR_MAX_IMAGE_PIXELS``     89,478,485  pixels of one image or frame
                                                                   (PIL's bomb threshold)
``points``              ``TAPTR_MAX_POINTS``           100,000     query points of one tracking
                                                                   call (CLI and Python API)
======================  =============================  ==========  ===============================

Values are integers; byte limits also accept the suffixes K, M, G and T (powers of 1024).
"""

from __future__ import annotations

import os
from typing import NamedTuple


class Limit(NamedTuple):
    """One limit: its environment variable, default, unit and what it bounds."""

    variable: str
    default: int
    unit: str
    description: str


LIMITS: dict[str, Limit] = {
    "file_bytes": Limit(
        "TAPTR_MAX_FILE_BYTES", 8 * 1024**3, "bytes", "one dataset file (pickle, .npy)"
    ),
    "checkpoint_bytes": Limit(
        "TAPTR_MAX_CHECKPOINT_BYTES", 4 * 1024**3, "bytes", "a checkpoint file and its tensors"
    ),
    "video_bytes": Limit(
        "TAPTR_MAX_VIDEO_BYTES", 4 * 1024**3, "bytes", "one video's decoded frames"
    ),
    "video_frames": Limit("TAPTR_MAX_VIDEO_FRAMES", 10_000, "frames", "one TAP-Vid video"),
    "image_pixels": Limit(
        "TAPTR_MAX_IMAGE_PIXELS", 89_478_485, "pixels", "one decoded image or frame"
    ),
    "points": Limit("TAPTR_MAX_POINTS", 100_000, "points", "query points of one tracking call"),
}
"""Every limit by name; docs/FAQ.md lists them for users."""

_SUFFIXES = {"K": 1024, "M": 1024**2, "G": 1024**3, "T": 1024**4}


class LimitError(ValueError):
    """A file declares more than a limit allows; the message says how to raise it."""


def limit(name: str) -> int:
    """The current value of limit ``name``: its environment variable, else its default.

    Raises:
        KeyError: unknown limit name.
        ValueError: the environment variable is not a positive integer.
    """
    entry = LIMITS[name]
    text = os.environ.get(entry.variable, "").strip()
    if not text:
        return entry.default
    scale = _SUFFIXES.get(text[-1].upper(), 1)
    digits = text[:-1] if scale > 1 else text
    if not digits.isdigit() or int(digits) < 1:
        raise ValueError(
            f"{entry.variable}={text!r} must be a positive integer (K, M, G, T allowed)"
        )
    return int(digits) * scale


def check(name: str, needed: int, what: str) -> None:
    """Raises `LimitError` when ``needed`` exceeds limit ``name``.

    Args:
        name: the limit, a key of `LIMITS`.
        needed: what the input declares (bytes, frames or pixels).
        what: the input and quantity for the message, e.g. ``"video.pkl: 20000 frames"``.
    """
    allowed = limit(name)
    if needed > allowed:
        entry = LIMITS[name]
        raise LimitError(
            f"{what} exceeds the limit of {allowed:,} {entry.unit} for {entry.description} "
            f"(set {entry.variable} higher to read it)"
        )
