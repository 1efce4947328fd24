"""``taptr sample-video PATH``: write the package's licence-clean sample clip."""

from __future__ import annotations

import argparse

from taptr.cli.common.options import MAX_INPUT_SIDE, check_output_file

MIN_SIDE = 16
"""Smallest side of a sample clip: the occluding disc needs a few pixels of its own."""

MAX_FRAMES = 100_000
"""Most frames of a sample clip (frames are rendered as they are encoded: time, not memory)."""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    parser = subparsers.add_parser(
        "sample-video",
        help="write a generated sample clip to track (48 frames, 256x256, no data needed)",
        description="Writes a procedural clip made by taptr itself (a textured scene under a known "
        "camera pan, zoom and roll, with a rolling disc that occludes the background), at 24 "
        "frames per second. --frames, --size and --seed make clips of other lengths, sizes and "
        "textures, e.g. a test corpus.",
    )
    parser.add_argument(
        "path", nargs="?", default="sample.mp4", help="output mp4 (default: sample.mp4)"
    )
    parser.add_argument(
        "--frames",
        type=int,
        default=48,
        metavar="N",
        help=f"frames of the clip, 2 to {MAX_FRAMES} (default: 48)",
    )
    parser.add_argument(
        "--size",
        type=int,
        nargs=2,
        default=(256, 256),
        metavar=("HEIGHT", "WIDTH"),
        help=f"frame size in pixels, each side {MIN_SIDE} to {MAX_INPUT_SIDE}; an odd side is "
        "padded by one pixel for H.264 (default: 256 256)",
    )
    parser.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the scene's textures: other seeds give other clips (default: 0)",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Writes the clip."""
    check_output_file(args.path, "PATH", suffixes=(".mp4",))
    _check(args)
    from taptr.data.sample_video import write_sample_video

    height, width = args.size
    path = write_sample_video(
        args.path, num_frames=args.frames, height=height, width=width, seed=args.seed
    )
    print(f"wrote {path}")
    return 0


def _check(args: argparse.Namespace) -> None:
    """Refuses a length, size or seed the clip cannot have, in one line."""
    if not 2 <= args.frames <= MAX_FRAMES:
        raise ValueError(f"--frames must lie in [2, {MAX_FRAMES}], got {args.frames}")
    if not all(MIN_SIDE <= side <= MAX_INPUT_SIDE for side in args.size):
        shown = " ".join(map(str, args.size))
        raise ValueError(f"--size {shown}: each side must lie in [{MIN_SIDE}, {MAX_INPUT_SIDE}]")
    if not 0 <= args.seed < 2**63:
        raise ValueError(f"--seed must lie in [0, 2**63), got {args.seed}")
