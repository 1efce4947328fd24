"""``taptr make-synthetic``: write procedural videos with exact tracks (Kubric layout)."""

from __future__ import annotations

import argparse


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    parser = subparsers.add_parser(
        "make-synthetic",
        help="write synthetic training/test videos with exact tracks",
        description="Writes OUT/00000, OUT/00001, ... in the Kubric MOVi-F layout "
        "(frames/000.png ..., <seq>.npy with coords and occlusion), readable by "
        "'taptr train' and taptr.data.kubric. Video i depends only on (--seed, i).",
    )
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--videos", type=int, required=True, help="number of videos")
    parser.add_argument("--seed", type=int, default=0, help="use another seed for a held-out set")
    parser.add_argument("--size", type=int, nargs=2, default=(256, 256), metavar=("H", "W"))
    parser.add_argument("--frames", type=int, default=24, help="frames per video")
    parser.add_argument("--points", type=int, default=1024, help="tracks per video")
    parser.add_argument(
        "--textures",
        metavar="DIR|builtin",
        help="texture layers with real photographs: a folder of images, or 'builtin' for the "
        "training split of taptr's built-in set (needs the photos extra; see "
        "taptr.data.photos). Tracks and occlusions stay exact",
    )
    parser.add_argument(
        "--photo-prob",
        type=float,
        default=0.8,
        help="with --textures: probability that a layer is a photograph (default: 0.8)",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Generates and reports the folder."""
    from tqdm import tqdm

    from taptr.data.synthetic import SyntheticConfig, write_dataset

    if args.videos < 1:
        raise ValueError("--videos must be at least 1")
    if not 0 <= args.photo_prob <= 1:
        raise ValueError("--photo-prob must be between 0 and 1")
    photos = None
    if args.textures:
        from taptr.data.photos import load_textures

        photos = load_textures(args.textures)
    config = SyntheticConfig(
        height=args.size[0], width=args.size[1], num_frames=args.frames, num_points=args.points
    )
    for index in tqdm(range(args.videos), desc="videos", disable=args.videos < 20):
        write_dataset(
            args.out,
            1,
            config,
            seed=args.seed,
            first=index,
            photos=photos,
            photo_prob=args.photo_prob,
        )
    textured = f" textured with {len(photos)} photographs" if photos else ""
    print(f"wrote {args.videos} videos{textured} to {args.out}")
    return 0
