"""What a path is, asked of ``stat`` before anything opens it.

Opening a FIFO for reading blocks until a writer appears, forever if none does; a device
such as ``/dev/zero`` reads without end; a socket cannot be opened at all. Every reader of
user files (videos, checkpoints, points files, masks, overlays, dataset files) asks
`require_file` (or `require_file_or_folder`) first, which only calls ``stat``: it never
blocks, and it refuses whatever is not a regular file with a one-line message saying what
the path is instead.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

KINDS = {
    stat.S_IFIFO: "a FIFO (named pipe)",
    stat.S_IFCHR: "a character device",
    stat.S_IFBLK: "a block device",
    stat.S_IFSOCK: "a socket",
    stat.S_IFDIR: "a folder",
}
"""What each kind of path that is not a regular file is called in messages."""

MAX_SHOWN = 120
"""Longest path shown in a message; a longer one is cut in the middle."""


def shown(path: str | os.PathLike[str]) -> str:
    """``path`` for a message, cut in the middle when it is longer than `MAX_SHOWN`."""
    text = os.fspath(path)
    if len(text) <= MAX_SHOWN:
        return text
    half = MAX_SHOWN // 2
    return f"{text[:half]}...{text[-half:]}"


def kind(path: str | os.PathLike[str], what: str) -> str | None:
    """``"file"``, ``"folder"`` or None (missing), from ``stat``; never opens the path.

    Args:
        path: the path to look at (symbolic links are followed).
        what: names the path in messages, e.g. ``"--points-file"`` or ``"checkpoint"``.

    Raises:
        ValueError: the path is a FIFO, device or socket, or cannot be looked at (a name
            too long, a loop of links, no permission); the message says which.
    """
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return None
    except NotADirectoryError:
        return None  # a component of the path is a file: nothing is there
    except OSError as error:
        reason = "the name is too long" if error.errno == errno.ENAMETOOLONG else error.strerror
        raise ValueError(f"{what} {shown(path)}: cannot look at it ({reason})") from None
    except ValueError:  # an embedded NUL byte
        raise ValueError(f"{what} {shown(path)!r}: not a valid path") from None
    if stat.S_ISREG(mode):
        return "file"
    if stat.S_ISDIR(mode):
        return "folder"
    described = KINDS.get(stat.S_IFMT(mode), "not a regular file")
    raise ValueError(f"{what} {shown(path)} is {described}, not a regular file")


def require_file(path: str | os.PathLike[str], what: str) -> Path:
    """``path`` as a Path when it is a regular file (or a link to one).

    Raises:
        FileNotFoundError: nothing is there.
        ValueError: it is a folder, FIFO, device or socket, or cannot be looked at.
    """
    found = kind(path, what)
    if found is None:
        raise FileNotFoundError(f"{what} {shown(path)}: not found")
    if found == "folder":
        raise ValueError(f"{what} {shown(path)} is a folder, not a file")
    return Path(path)


def require_file_or_folder(path: str | os.PathLike[str], what: str) -> Path:
    """``path`` as a Path when it is a regular file or a folder.

    Raises:
        FileNotFoundError: nothing is there.
        ValueError: it is a FIFO, device or socket, or cannot be looked at.
    """
    if kind(path, what) is None:
        raise FileNotFoundError(f"{what} {shown(path)}: not found")
    return Path(path)


def is_regular_file(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a regular file; False for anything else, even unreadable paths."""
    try:
        return stat.S_ISREG(os.stat(path).st_mode)
    except (OSError, ValueError):
        return False
