"""The options of every command that runs a model, and the predictor they describe."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from taptr.cli.options import (
    MAX_INPUT_SIDE,
    MIN_INPUT_SIDE,
    add_device_argument,
    check_at_least,
    check_device,
    check_input_size,
)
from taptr.types import AUTOCAST_TYPES

if TYPE_CHECKING:
    from taptr.api.predictor import Predictor

KERNEL_CHOICES = ("auto", "measure", "grid_sample", "gather")
"""``--kernel`` choices (`taptr.model.kernel_choice.CHOICES`; here so --help needs no torch)."""


def add_model_arguments(parser: argparse.ArgumentParser, max_frames: int | None = None) -> None:
    """Options shared by the commands that run a model (``max_frames``: its default)."""
    parser.add_argument(
        "--checkpoint",
        default=None,
        help="checkpoint file or model name (default: the paper's weights taptrv2-official "
        "from the Hugging Face cache or downloaded once; without network, the bundled "
        "taptr-small-synthetic, with a warning)",
    )
    add_device_argument(parser)
    parser.add_argument(
        "--context-points",
        type=int,
        default=None,
        metavar="K",
        help="pad the queries with seeded context points up to K points, as the official "
        "demo does; they are never written out; 0 turns it off (default: the model's, 800 "
        "for the paper's weights)",
    )
    parser.add_argument(
        "--input-size",
        type=int,
        nargs=2,
        metavar=("HEIGHT", "WIDTH"),
        default=None,
        help="resolution the model sees, each side in "
        f"[{MIN_INPUT_SIDE}, {MAX_INPUT_SIDE}] (default: the model's, 512 512 for the paper "
        "model)",
    )
    parser.add_argument(
        "--dtype",
        choices=AUTOCAST_TYPES,
        default="float32",
        help="run the model under autocast in this type, weights kept in float32 (float16 "
        "as the official demo runs, or bfloat16: for GPUs; accuracy in docs/BENCHMARKS.md) "
        "(default: float32, no autocast)",
    )
    parser.add_argument(
        "--kernel",
        choices=KERNEL_CHOICES,
        default="auto",
        help="deformable-attention kernel: auto measures gather against grid_sample on GPUs "
        "and uses gather on CPU; measure times both on any device (default: auto)",
    )
    parser.add_argument(
        "--compile",
        action="store_true",
        help="compile the model with torch.compile (slow first windows, then faster; needs "
        "a C++ compiler on CPU)",
    )
    parser.add_argument(
        "--max-frames",
        type=int,
        default=max_frames,
        help=f"read at most this many frames (default: {max_frames or 'all'})",
    )


def check_model_arguments(args: argparse.Namespace) -> None:
    """Checks the options of `add_model_arguments` before any file is read."""
    check_device(args.device)
    check_input_size(args.input_size)
    if args.context_points is not None:
        check_at_least(args.context_points, 0, "--context-points")
    check_at_least(args.max_frames, 1, "--max-frames")


def load_predictor(args: argparse.Namespace) -> Predictor:
    """The predictor the model arguments describe."""
    from taptr.api.predictor import Predictor, autocast_type

    size = tuple(args.input_size) if args.input_size else None
    predictor = Predictor.from_pretrained(
        args.checkpoint,
        device=args.device,
        input_size=size,
        context_points=args.context_points,
        autocast=autocast_type(args.dtype),
        kernel=args.kernel,
    )
    if args.compile:
        from taptr.export.compile import compile_model

        compile_model(predictor.model)
    return predictor
