"""The files of an export folder, looked at before anything reads them.

An export folder is copied between machines and edited by hand, so nothing in it is
trusted: each file the loop reads must be a regular file (a FIFO in place of a graph
would block an engine's open forever, a folder makes it fail with a parsing error),
and the manifest is read bounded (`MAX_MANIFEST_BYTES`). The file is opened without
blocking and asked what it is on the open descriptor, so a path swapped between the
check and the read cannot block either. Links are followed: a folder of links to a
shared model store reads as the files they name.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

from taptr.io.file_kind import KINDS, shown

MAX_MANIFEST_BYTES = 256 * 1024
"""Largest manifest read: TAPTRv3's is about 10 KB (its 63 local offsets, 36 grid points
and the graphs' tensors), so anything near this bound is not one of ours."""


def _open_regular(path: Path, what: str) -> int:
    """A descriptor of ``path`` opened for reading, when it is a regular file.

    Raises:
        FileNotFoundError: nothing is there.
        ValueError: a folder, FIFO, device or socket, or a path that cannot be opened.
    """
    try:
        descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # a FIFO opens at once
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} {shown(path)}: not found") from None
    except IsADirectoryError:
        raise ValueError(f"{what} {shown(path)} is a folder, not a regular file") from None
    except OSError as error:
        reason = "the name is too long" if error.errno == errno.ENAMETOOLONG else error.strerror
        raise ValueError(f"{what} {shown(path)}: cannot open it ({reason})") from None
    mode = os.fstat(descriptor).st_mode
    if not stat.S_ISREG(mode):
        os.close(descriptor)
        described = KINDS.get(stat.S_IFMT(mode), "not a regular file")
        raise ValueError(f"{what} {shown(path)} is {described}, not a regular file")
    return descriptor


def require_regular(path: str | os.PathLike[str], what: str) -> Path:
    """``path`` when it is a regular file (or a link to one); opened and closed, never read.

    Raises:
        FileNotFoundError: nothing is there.
        ValueError: a folder, FIFO, device or socket (the message says which).
    """
    os.close(_open_regular(Path(path), what))
    return Path(path)


def read_bounded(path: str | os.PathLike[str], limit: int, what: str) -> bytes:
    """The bytes of a regular file of at most ``limit`` bytes.

    Raises:
        FileNotFoundError: nothing is there.
        ValueError: not a regular file, or larger than ``limit``.
    """
    descriptor = _open_regular(Path(path), what)
    with os.fdopen(descriptor, "rb") as stream:
        data = stream.read(limit + 1)
    if len(data) > limit:
        raise ValueError(
            f"{what} {shown(path)}: larger than the {limit // 1024} KiB this file may hold"
        )
    return data
