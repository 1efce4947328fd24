"""``taptr download``: fetch named weights now, for a machine that will be offline later."""

from __future__ import annotations

import argparse


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers ``taptr download``."""
    parser = subparsers.add_parser(
        "download",
        help="fetch named weights ahead of time",
        description="Fetches named weights once, where taptr looks for them: the authors' "
        "TAPTRv2 (taptrv2-official) into the Hugging Face cache (needs the hub "
        "extra), TAPTRv3 (taptrv3-official, taptrv3-r50-official) from Google "
        "Drive into the weights folder (TAPTR_WEIGHTS_DIR, default ~/.cache/taptr/weights; "
        "needs the drive extra). Each licence is said before its download; a "
        "file that is not the weights its name promises is refused. Prints each file's path.",
    )
    parser.add_argument("names", nargs="+", metavar="NAME", help="weights to fetch")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Fetches each named file and prints where it is."""
    from taptr.weights import registry

    for name in args.names:
        print(f"{name}: {registry.download(name)}")
    return 0
