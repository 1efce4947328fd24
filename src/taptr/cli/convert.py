"""``taptr convert SRC DST``: write any checkpoint taptr can load in taptr's own format."""

from __future__ import annotations

import argparse

from taptr.cli.common.options import check_output_file
from taptr.io.file_kind import kind, require_file


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    parser = subparsers.add_parser(
        "convert",
        help="convert an official TAPTR checkpoint (or a taptr one) to taptr's format",
        description="Reads SRC safely (weights_only), converts official key names strictly, "
        "and writes DST atomically as {'format': 'taptr', 'version': 1, 'config', 'model'}.",
    )
    parser.add_argument("src", help="official release (e.g. taptrv2.pth) or a taptr checkpoint")
    parser.add_argument("dst", help="output file")
    parser.add_argument("--half", action="store_true", help="store weights as float16")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Converts and reports what was written."""
    check_output_file(args.dst, "DST")
    if kind(args.src, "checkpoint") is None:
        raise FileNotFoundError(f"checkpoint not found: {args.src}")
    require_file(args.src, "checkpoint")  # a folder, FIFO or device is named as such
    from taptr.weights.checkpoint import load_checkpoint, read_visibility_threshold, save_checkpoint

    model = load_checkpoint(args.src)
    threshold = read_visibility_threshold(args.src)  # a calibrated threshold travels along
    path = save_checkpoint(model, args.dst, half=args.half, visibility_threshold=threshold)
    params = sum(p.numel() for p in model.parameters())
    print(f"wrote {path}: {len(model.state_dict())} tensors, {params:,} parameters")
    return 0
