"""Entry point of the ``taptr`` command: one subcommand per module of this package.

`COMMANDS` lists them; what they share is `taptr.cli.common`, whose modules are no commands.
Each subcommand module defines ``add_parser(subparsers)``, which registers its parser and
sets ``func(args) -> int``. Every failure prints one line ``taptr COMMAND: error: ...``:
bad arguments and files exit with status 2 (so does a run whose estimated memory exceeds
what the machine has, `taptr.memory_estimate`), running out of memory anyway and bugs
with 1 (an allocator's failure names the knobs to turn; bugs say so, and ``-v`` shows their
traceback), Ctrl-C with 130 and SIGTERM with 143; temporary files are removed on the way
out. Before the command runs, `taptr.cli.common.guards` checks numeric options and
``TAPTR_MAX_*`` variables and quiets third-party log lines.
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import logging
import pickle
import re
import signal
import sys
import threading
import traceback
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import NoReturn

from taptr.cli.common import guards
from taptr.runtime import threads

COMMANDS = (
    "convert",
    "track",
    "track-corpus",
    "edit",
    "sample-video",
    "eval",
    "train",
    "make-synthetic",
    "make-photo-bench",
    "analyze",
    "bench",
    "export",
    "demo",
    "prepare-kinetics",
    "check-data",
    "calibrate",
    "download",
)

USER_ERRORS: tuple[type[BaseException], ...] = (
    FileNotFoundError,
    ValueError,
    KeyError,
    PermissionError,
    IsADirectoryError,
    NotADirectoryError,
    FileExistsError,
    pickle.UnpicklingError,
    NotImplementedError,  # e.g. weights of a model this version cannot build
    ModuleNotFoundError,  # an optional extra (demo, hub, export) is not installed
)


DASH_VALUE_FLAGS = ("--points",)
"""Options whose value may start with '-' (``--points -1,5,5`` is read as ``--points=-1,5,5``)."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that cleanup code runs (``finally`` blocks)."""


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line that points to ``--help``.

    Subparsers inherit the class, so every command's argument errors look alike.
    """

    def error(self, message: str) -> NoReturn:
        """Prints ``PROG: error: MESSAGE (see PROG --help)`` and exits with status 2."""
        hint = ""
        flag = re.match(r"argument ([^:/ ]+).*: expected one argument", message)
        if flag:
            hint = f"; a value that starts with '-' is written {flag.group(1)}=VALUE"
        self.exit(2, f"{self.prog}: error: {message}{hint} (see '{self.prog} --help')\n")

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        """Parses, after refusing a misspelled option of a command with the closest name.

        argparse reports a missing required option before an unknown one (``--gird 8``
        would read as "--grid is required"), and the unknown one in the top-level
        parser's name, without a suggestion.
        """
        if args is not None and not self._subparsers:
            unknown = unknown_option(self, list(args))
            if unknown is not None:
                self.error(unknown)
        return super().parse_known_args(args, namespace)


def unknown_option(parser: argparse.ArgumentParser, argv: list[str]) -> str | None:
    """The error for the first ``--option`` that ``parser`` does not have, or None.

    A unique prefix is an option (argparse accepts abbreviations); ``--`` ends the options.
    """
    known = [name for name in parser._option_string_actions if name.startswith("--")]
    for token in argv:
        if token == "--":
            return None
        if not token.startswith("--"):
            continue
        flag = token.split("=", 1)[0]
        if any(name.startswith(flag) for name in known):
            continue
        close = difflib.get_close_matches(flag, known, n=1, cutoff=0.6)
        hint = f"; did you mean {close[0]}?" if close else ""
        return f"unknown option {flag}{hint}"
    return None


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every subcommand registered."""
    from taptr import __version__

    parser = Parser(
        prog="taptr", description="Tracking Any Point with TAPTR v1, TAPTRv2 and TAPTRv3."
    )
    parser.add_argument("--version", action="version", version=f"taptr {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="store_true", help="log progress details and show tracebacks"
    )
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"taptr.cli.{name.replace('-', '_')}").add_parser(subparsers)
    for command in subparsers.choices.values():
        # `taptr track ... -v` works too; SUPPRESS keeps a -v given before the command
        command.add_argument(
            "-v",
            "--verbose",
            action="store_true",
            default=argparse.SUPPRESS,
            help=argparse.SUPPRESS,
        )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the command line; returns the exit status."""
    threads.sleep_when_idle()  # before any command imports torch
    parser = build_parser()
    args = parser.parse_args(join_dash_values(sys.argv[1:] if argv is None else list(argv)))
    handler = logging.StreamHandler()
    handler.setFormatter(LevelFormatter())
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, handlers=[handler])
    prefix = f"taptr {args.command}: error:"
    try:
        with sigterm_raises(), guards.clean_stderr():
            guards.check_numbers(parser, args)
            guards.check_limits()
            return int(args.func(args) or 0)
    except USER_ERRORS as error:
        if args.verbose:
            traceback.print_exc()
        message = error.args[0] if isinstance(error, KeyError) and error.args else error
        print(f"{prefix} {one_line(str(message))}", file=sys.stderr)
        return 2
    except OSError as error:  # a name too long, a full disk: about the user's files
        if guards.user_os_error(error) is None:
            return _failed(args, prefix, error)
        if args.verbose:
            traceback.print_exc()
        print(f"{prefix} {guards.user_os_error(error)}", file=sys.stderr)
        return 2
    except Terminated:
        print("terminated", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as error:  # the last resort: one line, not a traceback
        return _failed(args, prefix, error)


def _failed(args: argparse.Namespace, prefix: str, error: Exception) -> int:
    """Prints the last-resort line (out of memory, or a bug) and returns status 1."""
    if args.verbose:
        traceback.print_exc()
    print(f"{prefix} {describe_failure(error, args.command)}", file=sys.stderr)
    return 1


class LevelFormatter(logging.Formatter):
    """Progress details as they are; warnings and errors as ``taptr: warning: ...``."""

    def format(self, record: logging.LogRecord) -> str:
        """The message, prefixed with its level from WARNING up."""
        text = super().format(record)
        if record.levelno >= logging.WARNING:
            return f"taptr: {record.levelname.lower()}: {text}"
        return text


def join_dash_values(argv: list[str]) -> list[str]:
    """Joins ``--points -1,5,5`` into ``--points=-1,5,5``, which argparse would refuse."""
    joined: list[str] = []
    index = 0
    while index < len(argv):
        token = argv[index]
        value = argv[index + 1] if index + 1 < len(argv) else ""
        if token in DASH_VALUE_FLAGS and re.match(r"-[\d.]", value):
            joined.append(f"{token}={value}")
            index += 2
        else:
            joined.append(token)
            index += 1
    return joined


def one_line(message: str) -> str:
    """A message of several lines (a list of mismatched keys) as one: "; " between lines."""
    parts = [line.strip() for line in message.splitlines() if line.strip()]
    text = parts[0] if parts else ""
    for part in parts[1:]:
        text += (" " if text.endswith(":") else "; ") + part
    return text


def describe_failure(error: Exception, command: str) -> str:
    """One line for an exception that is not a user error: out of memory, or a bug."""
    from taptr.memory_estimate import allocator_failure

    text = " ".join(str(error).split())
    if len(text) > 300:
        text = text[:300] + " ..."
    out_of_memory = allocator_failure(error)
    if out_of_memory:
        return out_of_memory
    return (
        f"{type(error).__name__}: {text} (this is a bug in taptr; 'taptr -v {command} ...' "
        "shows the traceback to report)"
    )


@contextmanager
def sigterm_raises() -> Iterator[None]:
    """Turns SIGTERM into `Terminated` for the block, so temporary files get removed."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def _raise(_signum: int, _frame: object) -> None:
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, _raise)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


if __name__ == "__main__":
    sys.exit(main())
