"""The file of measured speed choices (`taptr.runtime.measured`), read and written carefully.

The file lives in the user's cache or wherever ``TAPTR_MEASURED`` points, so anything may be
there: a FIFO (opening it would block), a link to ``/dev/zero`` (reading it would never
end), a huge or deeply nested JSON document, values of the wrong type, or a file of the
user's that merely has the name. Reading it costs at most `MAX_BYTES` and never blocks;
whatever is wrong costs only a fresh measurement. The file is replaced only when it is
taptr's own (its ``format`` is `FORMAT`, or it is a flat table of choice keys written by
earlier versions), empty or missing; any other file is left as it is, said once per run.
"""

from __future__ import annotations

import json
import os
import stat
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from taptr.io.atomic import atomic_path
from taptr.io.file_kind import KINDS, shown

FORMAT = "taptr measured speed choices, version 1"
"""What taptr's file says it is, under the key ``format``."""

MAX_BYTES = 1024**2
"""Largest file read: a choice takes about 150 bytes, so this holds thousands of them."""

LEGACY_MARK = " | torch "
"""Part of every key (`taptr.runtime.measured.choice_key`): a flat table whose keys all
contain it was written by an earlier taptr and is taken as taptr's own."""

VARIABLE = "TAPTR_MEASURED"
"""The setting that names the file."""

_warned: set[str] = set()


@dataclass(frozen=True)
class Kept:
    """What the file holds.

    Attributes:
        choices: the measured choices by key (values still to be checked by their user).
        ours: whether the file may be replaced (taptr's own, empty or missing).
    """

    choices: dict[str, Any] = field(default_factory=dict)
    ours: bool = True


def _leave_alone(path: Path, reason: str) -> Kept:
    """Warns once per path that the file is not taptr's and will not be replaced."""
    if str(path) not in _warned:
        _warned.add(str(path))
        warnings.warn(
            f"{shown(path)} is not taptr's file of measured speed choices ({reason}): "
            f"left as it is, so speed choices are measured on every run; set {VARIABLE} to "
            "another file, or remove this one",
            stacklevel=3,
        )
    return Kept({}, ours=False)


def _read_bounded(path: Path) -> bytes | str:
    """The file's bytes, or why it is not read (a special file, too large, unreadable)."""
    try:
        # non-blocking: a FIFO swapped in after any stat could not hang the open
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as error:
        return f"cannot be opened: {error.strerror}"
    with os.fdopen(fd, "rb") as stream:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            return KINDS.get(stat.S_IFMT(mode), "not a regular file")
        try:
            data = stream.read(MAX_BYTES + 1)
        except OSError as error:
            return f"cannot be read: {error.strerror}"
    if len(data) > MAX_BYTES:
        return f"larger than {MAX_BYTES:,} bytes"
    return data


def _choices(document: Any) -> dict[str, Any] | None:
    """The choices of a parsed document of taptr's, or None for any other document."""
    if not isinstance(document, dict):
        return None
    if document.get("format") == FORMAT and isinstance(document.get("choices"), dict):
        return dict(document["choices"])
    if document and all(LEGACY_MARK in key for key in document):
        return dict(document)
    return None


def read_choices(path: str | os.PathLike[str]) -> Kept:
    """The choices kept in ``path``, and whether the file may be replaced; never raises."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return Kept()
    except (OSError, ValueError) as error:
        return _leave_alone(path, f"cannot be looked at: {error}")
    if not stat.S_ISREG(mode):
        return _leave_alone(path, KINDS.get(stat.S_IFMT(mode), "not a regular file"))
    data = _read_bounded(path)
    if isinstance(data, str):
        return _leave_alone(path, data)
    if not data.strip():
        return Kept()  # an empty file holds nothing to lose
    try:
        document = json.loads(data.decode("utf-8"))
    except RecursionError:
        return _leave_alone(path, "JSON nested too deeply")
    except (ValueError, UnicodeDecodeError):
        return _leave_alone(path, "not JSON")
    choices = _choices(document)
    if choices is None:
        return _leave_alone(path, f"JSON without format {FORMAT!r}")
    return Kept(choices)


def write_choices(path: str | os.PathLike[str], choices: dict[str, Any]) -> None:
    """Replaces taptr's file with ``choices``, atomically; a failure is ignored.

    A link is followed, so a file kept elsewhere through a link stays there.
    """
    document = {"format": FORMAT, "choices": choices}
    try:
        with atomic_path(os.path.realpath(path)) as tmp:
            tmp.write_text(json.dumps(document, indent=1, sort_keys=True))
    except OSError:
        pass  # a read-only home: measured again next time, tracking goes on
