"""``taptr sample-video PATH``: write the package's licence-clean sample clip."""

from __future__ import annotations

import argparse

from taptr.cli.common.options import check_output_file


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    parser = subparsers.add_parser(
        "sample-video",
        help="write a generated sample clip to track (48 frames, 256x256, no data needed)",
        description="Writes a procedural clip made by taptr itself (a textured scene under a known "
        "camera pan, zoom and roll, with a rolling disc that occludes the background).",
    )
    parser.add_argument(
        "path", nargs="?", default="sample.mp4", help="output mp4 (default: sample.mp4)"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Writes the clip."""
    from taptr.data.sample_video import write_sample_video

    check_output_file(args.path, "PATH", suffixes=(".mp4",))
    print(f"wrote {write_sample_video(args.path)}")
    return 0
