"""Text for people: an exception as one line, and names made safe to print.

A corpus job reports thousands of errors and ids on a terminal and in logs. An error must
stay one line (a progress log is read line by line), and an id from a manifest must not
bring its own newlines or terminal escapes (which forge lines or clear the screen).
"""

from __future__ import annotations

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
