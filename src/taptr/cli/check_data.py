"""``taptr check-data ROOT``: check a Kubric-layout dataset folder before using it."""

from __future__ import annotations

import argparse
import sys

DESCRIPTION = """\
Reads every sequence of a dataset in the Kubric MOVi-F layout (the layout of 'taptr train',
'taptr eval --dataset kubric' and 'taptr make-synthetic'):

  ROOT/<seq>/frames/000.png, 001.png, ...    RGB frames of one size
  ROOT/<seq>/<seq>.npy                       {"coords": (N, T, 2) pixel (x, y),
                                              "visibility": (N, T) bool, True = OCCLUDED}

with the reader training uses, and reports sequences that cannot be read (errors) and data
that loads but looks wrong (warnings: normalised coordinates, inverted occlusion flags,
tracks never visible, short sequences). Exit status 0 when there is no error, 1 otherwise.
"""

MAX_SHOWN = 20
"""Findings printed per level; the rest are counted."""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    parser = subparsers.add_parser(
        "check-data",
        help="check a Kubric-layout dataset folder (frames and .npy tracks)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("root", help="folder holding the sequence folders")
    parser.add_argument(
        "--max-sequences", type=int, metavar="N", help="check only the first N sequences"
    )
    parser.add_argument(
        "--min-frames",
        type=int,
        default=8,
        help="warn about sequences with fewer frames (default 8, one window)",
    )
    parser.add_argument(
        "--strict", action="store_true", help="exit 1 on warnings too, not only on errors"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Checks the folder and prints the summary and the findings."""
    from taptr.data.check import check_kubric_folder

    if args.max_sequences is not None and args.max_sequences < 1:
        raise ValueError("--max-sequences must be at least 1")
    report = check_kubric_folder(
        args.root, max_sequences=args.max_sequences, min_frames=args.min_frames, progress=True
    )
    print("\n".join(report.summary()))
    for level, findings in (("error", report.errors), ("warning", report.warnings)):
        for finding in findings[:MAX_SHOWN]:
            print(f"{level}: {finding.where}: {finding.message}", file=sys.stderr)
        if len(findings) > MAX_SHOWN:
            print(f"... and {len(findings) - MAX_SHOWN} more {level}s", file=sys.stderr)
    failed = bool(report.errors) or (args.strict and bool(report.warnings))
    print(
        f"{len(report.errors)} errors, {len(report.warnings)} warnings: "
        + ("FAILED" if failed else "ok")
    )
    return 1 if failed else 0
