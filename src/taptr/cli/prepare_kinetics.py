"""``taptr prepare-kinetics``: TAP-Vid-Kinetics shards from the label CSV and local clips."""

from __future__ import annotations

import argparse

DESCRIPTION = """\
Builds the 10 TAP-Vid-Kinetics pickles (0000_of_0010.pkl ... 0009_of_0010.pkl) in the
layout of tapnet's generate_tapvid.py, which 'taptr eval --dataset kinetics' and other
TAP-Vid readers expect: frames resampled to 25 fps, at most 250, JPEG-encoded; points
normalised with the generator's half-pixel shift. Clips are the Kinetics-700-2020
validation videos you downloaded, named {youtube_id}_{start:06}_{end:06}.mp4, in any
sub-folder of CLIPS. Clips that are missing are skipped and listed.
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    parser = subparsers.add_parser(
        "prepare-kinetics",
        help="build the TAP-Vid-Kinetics pickles from the label CSV and downloaded clips",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("csv", help="the label file, tapvid_kinetics.csv")
    parser.add_argument("clips", help="folder holding the downloaded .mp4 clips (any depth)")
    parser.add_argument(
        "--out",
        default="data/tapvid/tapvid_kinetics",
        help="output folder (default: data/tapvid/tapvid_kinetics)",
    )
    parser.add_argument("--shards", type=int, default=10, help="number of files (default 10)")
    parser.add_argument(
        "--jpeg-quality", type=int, default=95, help="JPEG quality of the frames (default 95)"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Writes the shards and reports what was skipped."""
    from taptr.data.prepare_kinetics import prepare_kinetics

    if not 1 <= args.jpeg_quality <= 100:
        raise ValueError(f"--jpeg-quality must lie in [1, 100], got {args.jpeg_quality}")
    report = prepare_kinetics(
        args.csv,
        args.clips,
        args.out,
        num_shards=args.shards,
        jpeg_quality=args.jpeg_quality,
        progress=True,
    )
    if report.missing:
        shown = ", ".join(report.missing[:5]) + (" ..." if len(report.missing) > 5 else "")
        print(f"skipped {len(report.missing)} clips that are not under {args.clips}: {shown}")
    print(
        f"wrote {len(report.videos)} videos ({report.num_points} tracks) to "
        f"{len(report.shards)} shards in {args.out}"
    )
    return 0
