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
``memory``              ``TAPTR_MAX_MEMORY``           (unset)     a tracking run's estimated peak
                                                                   memory (`taptr.memory_estimate`);
                                                                   unset: what the machine has
======================  =============================  ==========  ===============================

Values are whole numbers; byte limits also accept the suffixes K, M, G and T (powers of
1024). A value that is not one (``1.5G``, ``-1``, ``lots``) is an error naming the variable,
never ignored: `check_environment` checks every ``TAPTR_MAX_*`` variable when a command
starts, and each reader checks its own when it reads it.

Streamed reading (``taptr track`` and ``taptr edit`` decode, track and encode frame by frame)
never holds a whole video, so ``video_bytes`` bounds it only when its variable is set; the
``image_pixels`` limit bounds every frame on every path.
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
    "memory": Limit(
        "TAPTR_MAX_MEMORY", 0, "bytes", "a tracking run's estimated peak memory (0: unset)"
    ),
}
"""Every limit by name; docs/FAQ.md lists them for users."""

_SUFFIXES = {"K": 1024, "M": 1024**2, "G": 1024**3, "T": 1024**4}

PREFIX = "TAPTR_MAX_"
"""Every limit's variable starts so; `check_environment` looks at all such variables."""

MAX_DIGITS = 19
"""Longest number accepted: a limit beyond 10**19 means no limit, and longer digit strings
would only make int() slow."""


class LimitError(ValueError):
    """A file declares more than a limit allows; the message says how to raise it."""


def limit(name: str) -> int:
    """The current value of limit ``name``: its environment variable, else its default.

    Raises:
        KeyError: unknown limit name.
        ValueError: the environment variable is not a positive whole number (the message
            names the variable and the syntax).
    """
    entry = LIMITS[name]
    text = os.environ.get(entry.variable, "").strip()
    return parse(entry, text) if text else entry.default


def is_set(name: str) -> bool:
    """Whether the user set limit ``name``'s variable (to anything but blanks)."""
    return bool(os.environ.get(LIMITS[name].variable, "").strip())


def parse(entry: Limit, text: str) -> int:
    """The value ``text`` gives limit ``entry``.

    Raises:
        ValueError: ``text`` is not a positive whole number (with K, M, G or T for bytes).
    """
    scale = _SUFFIXES.get(text[-1:].upper(), 1) if entry.unit == "bytes" else 1
    digits = text[:-1] if scale > 1 else text
    if not (digits.isascii() and digits.isdigit()) or len(digits) > MAX_DIGITS or not int(digits):
        suffixes = ", optionally followed by K, M, G or T (powers of 1024)"
        example = "e.g. 1536M" if entry.unit == "bytes" else "e.g. 20000"
        raise ValueError(
            f"{entry.variable}={text[:40]!r} is not a valid limit: write a positive whole "
            f"number of {entry.unit}{suffixes if entry.unit == 'bytes' else ''} ({example})"
        )
    return int(digits) * scale


def check_environment() -> list[str]:
    """Checks every ``TAPTR_MAX_*`` variable; returns the names that are no taptr limit.

    Raises:
        ValueError: a limit's variable does not parse (the message names it and the syntax).
    """
    known = {entry.variable: entry for entry in LIMITS.values()}
    unknown = []
    for variable, text in sorted(os.environ.items()):
        if not variable.startswith(PREFIX) or not text.strip():
            continue
        if variable in known:
            parse(known[variable], text.strip())
        else:
            unknown.append(variable)
    return unknown


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
