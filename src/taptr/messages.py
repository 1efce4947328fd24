"""Text for people: an exception as one line, names made safe to print, install lines.

A corpus job reports thousands of errors and ids on a terminal and in logs. An error must
stay one line (a progress log is read line by line), and an id from a video list must not
bring its own newlines or terminal escapes (which forge lines or clear the screen). A
missing optional package is named with the command that installs it (`install_line`).
"""

from __future__ import annotations

import importlib.metadata
import shlex

MAX_ERROR_CHARS = 500
"""Longest error line kept: the start of a message says what went wrong."""


def error_line(error: BaseException) -> str:
    """An exception as one line: its message, or its type where the message alone is unclear.

    Errors about the user's input (ValueError, OSError and their kind) speak for themselves;
    others are prefixed with their type.
    """
    text = " ".join(str(error).split())
    if len(text) > MAX_ERROR_CHARS:
        text = text[:MAX_ERROR_CHARS] + " ..."
    if isinstance(error, (ValueError, OSError)) and text:
        return text
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def printable(text: str) -> str:
    r"""``text`` with control and other unprintable characters escaped (``\n``, ``\x1b``)."""
    if text.isprintable():
        return text
    return "".join(char if char.isprintable() else repr(char)[1:-1] for char in text)


def install_line(extra: str) -> str:
    """The pip command that installs the packages of taptr's optional ``extra``.

    It names the packages with their bounds, read from the installed package's metadata
    (pyproject.toml's extras): installing the extra by taptr's name fails from a checkout
    until taptr is on the package index, and ``pip install -e '.[extra]'`` fails outside one.
    Where taptr's metadata cannot be read, the checkout's form is given.
    """
    marker = f'extra == "{extra}"'
    try:
        requirements = importlib.metadata.requires("taptr") or []
    except importlib.metadata.PackageNotFoundError:
        requirements = []
    wanted = [r.split(";")[0].strip() for r in requirements if marker in r]
    if not wanted:
        return f"pip install -e '.[{extra}]'"
    return "pip install " + " ".join(shlex.quote(name) for name in wanted)
