"""The options of every command that runs a model, and the predictor they describe."""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import TYPE_CHECKING

from taptr.api.spec import ModelSpec
from taptr.cli.common.options import (
    MAX_INPUT_SIDE,
    MIN_INPUT_SIDE,
    add_device_argument,
    add_frames_per_call_argument,
    add_threads_argument,
    check_at_least,
    check_device,
    check_input_size,
)
from taptr.config import SUPPORT_KINDS, check_history_frames
from taptr.types import CAPTURE_CHOICES, DTYPE_CHOICES, ENGINE_CHOICES

if TYPE_CHECKING:
    from taptr.api.predictor import Predictor

CHECKPOINT_HELP = (
    "checkpoint file or model name (default: the paper's weights taptrv2-official, IDEA "
    "License 1.0, non-commercial, from the Hugging Face cache or downloaded once; without "
    "them, the bundled taptr-small-synthetic, Apache-2.0, with a warning)"
)
"""Help of every ``--checkpoint`` option that loads a model (`registry.DEFAULT_MODEL`)."""

CHECKPOINT_SUFFIXES = (".pth", ".pt", ".ckpt", ".bin", ".tar", ".pkl", ".safetensors")
"""File suffixes that make a missing ``--checkpoint`` a missing file rather than a name."""

KERNEL_CHOICES = ("auto", "measure", "grid_sample", "gather")
"""``--kernel`` choices (`taptr.runtime.kernel_choice.CHOICES`; here so --help needs no torch)."""

SUPPORT_CHOICES = ("auto", *SUPPORT_KINDS)
"""``--support`` choices: the model config's kinds and ``auto``."""


def add_model_arguments(
    parser: argparse.ArgumentParser, max_frames: int | None = None, engines: bool = False
) -> None:
    """Options shared by the commands that run a model (``max_frames``: its default).

    ``engines``: the command also runs exported graphs (``--engine``; ``track`` and
    ``track-corpus``); the others run PyTorch's model, whose modules they reach into.
    """
    parser.add_argument("--checkpoint", default=None, help=CHECKPOINT_HELP)
    if engines:
        add_engine_argument(parser)
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
        "--support",
        choices=SUPPORT_CHOICES,
        default="auto",
        help="extra points the model sees around the queries, never written out: random "
        "(up to --context-points, TAPTRv2's recipe), local_and_grid (63 around each query "
        "and a 6x6 grid, TAPTRv3's evaluation), grid (the grid only), none; auto: the "
        "model's own, with TAPTRv3 falling back to grid above 32 queries (default: auto)",
    )
    parser.add_argument(
        "--history-frames",
        type=int,
        default=None,
        metavar="N",
        help="TAPTRv3: past frames each point's long-temporal attention holds, the current "
        "one included, oldest dropped first (bounds memory on long videos; 0 holds the "
        "whole video, about 1 KiB per point and frame) (default: the model's, 0)",
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
        choices=DTYPE_CHOICES,
        default="float32",
        help="run the model under autocast in this type, weights kept in float32 (float16 "
        "as the official demo runs, or bfloat16; on the CPU, bfloat16 runs the products in "
        "bfloat16 where the CPU has it natively, AVX512-BF16 or AMX, else float32); with "
        "--engine onnxruntime or openvino: the engine's precision, bfloat16 (OpenVINO) or "
        "int8 (the encoder quantised once, calibrated on frames the package makes); accuracy "
        "in docs/BENCHMARKS.md (default: float32, no autocast)",
    )
    parser.add_argument(
        "--kernel",
        choices=KERNEL_CHOICES,
        default="auto",
        help="deformable-attention kernel: auto measures gather against grid_sample on GPUs "
        "and uses gather on CPU; measure times both on any device (default: auto)",
    )
    add_frames_per_call_argument(parser)
    parser.add_argument(
        "--compile",
        action="store_true",
        help="compile the model with torch.compile (slow first windows, then faster; needs "
        "a C++ compiler on CPU)",
    )
    parser.add_argument(
        "--capture",
        choices=CAPTURE_CHOICES,
        default="auto",
        help="TAPTRv3: compile its per-frame decoder step once and replay it (CUDA graphs on "
        "GPUs, Inductor on CPUs; speed only): auto where a measurement kept for this machine "
        "says it saves more than it costs over the video (a long video measures it on the "
        "job), on, or off (default: auto)",
    )
    add_threads_argument(parser)
    parser.add_argument(
        "--max-frames",
        type=int,
        default=max_frames,
        help=f"read at most this many frames (default: {max_frames or 'all'})",
    )


ENGINE_HELP = (
    "what runs the model: torch, or TAPTRv3's exported graphs on the CPU in onnxruntime or "
    "openvino (the checkpoint is exported once, a minute for the paper's model, into "
    "$TAPTR_EXPORT_DIR or ~/.cache/taptr/exports and reused; the same tracks up to float "
    "rounding; --threads is the engine's; docs/EXPORT.md) (default: torch)"
)
"""Help of ``--engine``."""


def add_engine_argument(parser: argparse.ArgumentParser) -> None:
    """``--engine``: PyTorch or a graph engine (`taptr.types.ENGINE_CHOICES`)."""
    parser.add_argument("--engine", choices=ENGINE_CHOICES, default="torch", help=ENGINE_HELP)


def check_model_arguments(args: argparse.Namespace) -> None:
    """Checks the options of `add_model_arguments` before any file is read, without torch.

    ``--device`` is checked by `load_predictor`, after the cheaper checks of the command:
    asking about a GPU imports torch, which takes seconds.
    """
    check_input_size(args.input_size)
    if args.context_points is not None:
        check_at_least(args.context_points, 0, "--context-points")
    if args.history_frames is not None:
        check_history_frames(args.history_frames, "--history-frames")
    check_at_least(args.max_frames, 1, "--max-frames")
    if args.threads is not None:
        check_at_least(args.threads, 1, "--threads")
    check_checkpoint_name(args.checkpoint)
    if getattr(args, "engine", "torch") != "torch":
        check_graph_device(args)
    check_dtype_engine(args.dtype, getattr(args, "engine", "torch"))


def check_dtype_engine(dtype: str, engine: str) -> None:
    """Refuses a ``--dtype`` that ``--engine`` does not run, before any model loads.

    Raises:
        ValueError: int8 with PyTorch, or float16 with a graph engine (CPU only).
    """
    if dtype == "int8" and engine == "torch":
        raise ValueError(
            "--dtype int8 runs in the graph engines: add --engine onnxruntime or "
            "--engine openvino (PyTorch runs float32, bfloat16 or float16)"
        )
    if dtype == "float16" and engine != "torch":
        raise ValueError(
            f"--engine {engine} runs float32, bfloat16 (openvino) or int8, not float16; "
            "use --engine torch on a GPU for float16"
        )


def check_checkpoint_name(checkpoint: str | None, flag: str = "--checkpoint") -> None:
    """Raises FileNotFoundError for a ``--checkpoint`` that is written as a missing file.

    Model names contain no folder and no checkpoint suffix, so ``runs/x/best.pth`` or
    ``taptrv2.pth`` that does not exist is a mistyped or missing file, said before torch
    loads; any other string is left to the model loader, which lists the names it knows.
    """
    if checkpoint is None or Path(checkpoint).exists():
        return
    folder = any(sep in checkpoint for sep in ("/", os.sep))
    if folder or Path(checkpoint).suffix.lower() in CHECKPOINT_SUFFIXES:
        raise FileNotFoundError(f"{flag} {checkpoint}: file not found")


def model_spec(args: argparse.Namespace) -> ModelSpec:
    """The tracker the model arguments describe, as a picklable `ModelSpec`."""
    return ModelSpec(
        checkpoint=args.checkpoint,
        device=args.device,
        dtype=args.dtype,
        input_size=tuple(args.input_size) if args.input_size else None,
        context_points=args.context_points,
        support=None if args.support == "auto" else args.support,
        history_frames=args.history_frames,
        kernel=args.kernel,
        frames_per_call=args.frames_per_call,
        capture=args.capture,
        compile=args.compile,
        threads=args.threads,
        engine=getattr(args, "engine", "torch"),
    )


def load_predictor(args: argparse.Namespace) -> Predictor:
    """The predictor the model arguments describe (``--device`` is checked first).

    A graph engine (``--engine onnxruntime``) gives a `taptr.api.graph_predictor.GraphPredictor`
    with the same surface.
    """
    if getattr(args, "engine", "torch") == "torch":
        check_device(args.device)  # a graph engine's: checked with the other arguments
    # a GraphPredictor has the surface the commands use: typed as the one they were written for
    return model_spec(args).load()  # type: ignore[return-value]


def check_graph_device(args: argparse.Namespace) -> None:
    """Refuses a GPU for a graph engine, which runs on the CPU.

    Raises:
        ValueError: ``--device`` names anything but the CPU.
    """
    if args.device not in (None, "cpu"):
        raise ValueError(
            f"--engine {args.engine} runs on the CPU; drop --device {args.device} or use "
            "--engine torch"
        )
