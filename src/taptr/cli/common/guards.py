"""What every command checks and quiets before it runs, so stderr holds our lines only.

- Numeric options: argparse's ``type=int`` takes any integer (``--max-frames 10**20`` later
  fails inside ``itertools.islice`` with its own message) and ``type=float`` takes ``nan``;
  `check_numbers` refuses both with a message naming the flag, before the command runs.
  Each command still checks its own ranges.
- Limits: every ``TAPTR_MAX_*`` variable is parsed (`taptr.io.limits.check_environment`);
  a value such as ``1.5G`` is an error naming the variable, and a name that is no limit
  (a typo) gets one warning.
- Noise: Python warnings are printed as one ``taptr: warning: ...`` line each (not with
  the source line that raised them), and OpenCV's and FFmpeg's own log lines are silenced:
  taptr reports what went wrong in its own messages.
- File-system errors that are about the user's paths (a name too long, a loop of links,
  a full or read-only disk) are user errors: `user_os_error` words them.
"""

from __future__ import annotations

import argparse
import errno
import logging
import math
import os
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager

MAX_OPTION_VALUE = 2**31 - 1
"""Largest magnitude of a numeric option: beyond any frame count, size or point count."""

USER_ERRNOS = {
    errno.ENAMETOOLONG: "the name is too long",
    errno.ELOOP: "too many levels of symbolic links",
    errno.ENOSPC: "no space left on the device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EROFS: "read-only file system",
    errno.EFBIG: "file too large for the file system",
    errno.ENXIO: "no such device or address",
    errno.ENODEV: "no such device",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
}
"""errno values that say something about the user's paths or disk, not about taptr."""

logger = logging.getLogger("taptr")


def check_numbers(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuses non-finite or huge values of the numeric options of the command run.

    Raises:
        ValueError: naming the flag and the value.
    """
    for action in _actions(parser, args):
        if action.type not in (int, float) or not hasattr(args, action.dest):
            continue
        value = getattr(args, action.dest)
        flag = max(action.option_strings, key=len) if action.option_strings else action.dest
        for number in value if isinstance(value, (list, tuple)) else [value]:
            if number is None or isinstance(number, bool):
                continue
            if isinstance(number, float) and not math.isfinite(number):
                raise ValueError(f"{flag} {number}: not a finite number")
            if abs(number) > MAX_OPTION_VALUE:
                raise ValueError(
                    f"{flag} {_shown_number(number)}: too large (at most {MAX_OPTION_VALUE:,})"
                )


def _shown_number(number: int | float) -> str:
    text = str(number) if isinstance(number, float) or abs(number) < 10**30 else f"{number:.3e}"
    return text


def _actions(
    parser: argparse.ArgumentParser, args: argparse.Namespace
) -> Iterator[argparse.Action]:
    """The actions of the parsers ``args`` went through: the command's, and any sub-command's."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            chosen = action.choices.get(getattr(args, action.dest, None) or "")
            if chosen is not None:
                yield from _actions(chosen, args)
        else:
            yield action


def check_limits() -> None:
    """Parses every ``TAPTR_MAX_*`` variable; warns once about names that are no limit."""
    from taptr.io import limits

    unknown = limits.check_environment()
    if unknown:
        known = ", ".join(entry.variable for entry in limits.LIMITS.values())
        logger.warning("ignoring %s: not a taptr limit (the limits: %s)", ", ".join(unknown), known)


@contextmanager
def clean_stderr() -> Iterator[None]:
    """One line per Python warning, and no log lines from OpenCV or FFmpeg, for the block."""
    os.environ.setdefault("OPENCV_LOG_LEVEL", "OFF")  # read when cv2 is first imported
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    if "cv2" in sys.modules:
        cv2 = sys.modules["cv2"]
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    if "av" in sys.modules:
        sys.modules["av"].logging.set_level(None)
    # the format, not the display: whoever records warnings (pytest, a caller's
    # catch_warnings) still receives them
    previous = warnings.formatwarning
    warnings.formatwarning = _one_line_warning
    try:
        yield
    finally:
        warnings.formatwarning = previous


def _one_line_warning(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    line: str | None = None,
) -> str:
    """``taptr: warning: MESSAGE`` on one line, without the source line Python adds."""
    return f"taptr: warning: {' '.join(str(message).split())}\n"


def user_os_error(error: OSError) -> str | None:
    """A one-line message for a file-system error about the user's paths, else None."""
    reason = USER_ERRNOS.get(error.errno or 0)
    if reason is None:
        return None
    from taptr.io.file_kind import shown

    names = [n for n in (error.filename, error.filename2) if n is not None]
    where = " -> ".join(shown(os.fsdecode(n)) for n in names)
    return f"{where}: {reason}" if where else reason
