"""Entry point of the ``taptr`` command: one subcommand per module of this package.

Each subcommand module defines ``add_parser(subparsers)``, which registers its parser and
sets ``func(args) -> int``. Expected failures (bad files, bad arguments) print one line and
exit non-zero without a traceback; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pickle
import sys
from collections.abc import Sequence

COMMANDS = (
    "convert",
    "track",
    "edit",
    "sample-video",
    "eval",
    "train",
    "make-synthetic",
    "bench",
    "export",
    "demo",
    "prepare-kinetics",
    "check-data",
    "calibrate",
)

USER_ERRORS: tuple[type[BaseException], ...] = (
    FileNotFoundError,
    ValueError,
    KeyError,
    PermissionError,
    pickle.UnpicklingError,
    NotImplementedError,  # e.g. weights of a model this version cannot build
    ModuleNotFoundError,  # an optional extra (demo, hub, export) is not installed
)


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every subcommand registered."""
    from taptr import __version__

    parser = argparse.ArgumentParser(prog="taptr", description="TAPTRv2 point tracking.")
    parser.add_argument("--version", action="version", version=f"taptr {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"taptr.cli.{name.replace('-', '_')}").add_parser(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the command line; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s"
    )
    try:
        return int(args.func(args) or 0)
    except USER_ERRORS as error:
        message = error.args[0] if isinstance(error, KeyError) and error.args else error
        print(f"taptr {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
