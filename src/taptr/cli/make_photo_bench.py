"""``taptr make-photo-bench``: held-out photographs moved by known warps, as a TAP-Vid pickle."""

from __future__ import annotations

import argparse


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    parser = subparsers.add_parser(
        "make-photo-bench",
        help="write a real-photo tracking benchmark (TAP-Vid DAVIS format)",
        description="Writes one pickle of videos in which held-out photographs move by known "
        "smooth warps (camera homographies, moving cut-outs) behind a sweeping occluder, with "
        "exact tracks and occlusion, in TAP-Vid DAVIS format: score a tracker with 'taptr eval "
        "--dataset davis --root OUT'. The default photographs are the held-out split of "
        "taptr's built-in set (the photos extra), never used by 'make-synthetic "
        "--textures builtin'. Video i depends only on (--seed, i) and the photographs.",
    )
    parser.add_argument("--out", required=True, help="the pickle file to write")
    parser.add_argument("--videos", type=int, default=10, help="number of videos (default: 10)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the set (default: 0)")
    parser.add_argument("--size", type=int, nargs=2, default=(256, 256), metavar=("H", "W"))
    parser.add_argument("--frames", type=int, default=24, help="frames per video (default: 24)")
    parser.add_argument("--points", type=int, default=256, help="tracks per video (default: 256)")
    parser.add_argument(
        "--photos",
        default="heldout",
        metavar="DIR|heldout",
        help="a folder of images, or 'heldout' for the built-in held-out photographs (default)",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Generates the benchmark and reports the file."""
    from taptr.data.photo_bench import PhotoBenchConfig, write_photo_bench
    from taptr.data.photos import load_builtin_photos, load_photo_folder

    if args.videos < 1:
        raise ValueError("--videos must be at least 1")
    if args.photos == "heldout":
        photos = load_builtin_photos("heldout")
    else:
        photos = load_photo_folder(args.photos)
    config = PhotoBenchConfig(
        height=args.size[0], width=args.size[1], num_frames=args.frames, num_points=args.points
    )
    path = write_photo_bench(args.out, args.videos, photos, config, seed=args.seed)
    print(f"wrote {args.videos} videos from {len(photos)} photographs to {path}")
    return 0
