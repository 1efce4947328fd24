"""``taptr export --format onnx|torchscript --out DIR``: the model's step as graphs.

TAPTR v1 and v2: three graphs (frames → memory, memory → initial point content, one window
of the decoder with its carried state) and ``taptr-export.json`` (input size, window
rules), enough for a sliding-window loop outside Python; ``taptr.export.graph_runner`` drives
them with the model's own window driver. TAPTRv3 (ONNX): the frame encoder, the step that
starts points and the per-frame decoder step with all its state as inputs and outputs,
and a manifest with every rule of the frame loop, which ``taptr.onnx.OnnxTracker`` runs
without torch. ``--check`` tracks the package's sample clip with both the model and the
graphs and prints the largest differences and the time each took.
"""

from __future__ import annotations

import argparse
import time

from taptr.cli.common.model_options import CHECKPOINT_HELP, check_checkpoint_name
from taptr.cli.common.options import check_at_least, check_input_size, check_output_folder
from taptr.config import check_history_frames


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    parser = subparsers.add_parser(
        "export",
        help="export the model's step as ONNX or TorchScript graphs",
        description="Writes encoder, init_points and decode_window graphs (batch 1; dynamic "
        "frame and point counts) and taptr-export.json to --out; for TAPTRv3 (ONNX only) "
        "encoder, start_points and decode_step graphs (dynamic point count and history "
        "length) and a manifest of the frame loop. See docs/EXPORT.md.",
    )
    parser.add_argument("--format", required=True, choices=("onnx", "torchscript"))
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--checkpoint", default=None, help=CHECKPOINT_HELP)
    parser.add_argument(
        "--input-size",
        type=int,
        nargs=2,
        metavar=("HEIGHT", "WIDTH"),
        default=None,
        help="frame size the graphs take (default: the model's, 512 512 for the paper model)",
    )
    parser.add_argument(
        "--history-frames",
        type=int,
        default=None,
        metavar="N",
        help="TAPTRv3: the history limit the manifest gives the loop (past frames held per "
        "point, the current one included, oldest dropped first; 0 holds every frame) "
        "(default: the model's)",
    )
    parser.add_argument(
        "--check",
        action="store_true",
        help="compare the graphs with the model on the sample clip and time both (CPU)",
    )
    parser.add_argument(
        "--check-frames", type=int, default=11, help="clip length for --check (default 11)"
    )
    parser.add_argument(
        "--check-points", type=int, default=8, help="points for --check (default 8)"
    )
    parser.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="--check times each runtime this often and keeps the best (default 1)",
    )
    parser.add_argument(
        "--threads", type=int, default=None, help="CPU threads for --check (both runtimes)"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Exports, then optionally checks parity and speed."""
    check_output_folder(args.out)
    check_input_size(args.input_size)
    for flag in ("check_frames", "check_points", "repeats", "threads"):
        check_at_least(getattr(args, flag), 1, "--" + flag.replace("_", "-"))
    if args.history_frames is not None:
        check_history_frames(args.history_frames, "--history-frames")
    check_checkpoint_name(args.checkpoint)
    import torch

    from taptr.export.graphs import export_model
    from taptr.export.manifest import GRAPHS
    from taptr.export.verify import compare
    from taptr.onnx.v3_manifest import V3Manifest
    from taptr.onnx.v3_tensors import GRAPHS as V3_GRAPHS
    from taptr.weights.registry import resolve_model

    if args.threads:
        torch.set_num_threads(args.threads)
    model = resolve_model(args.checkpoint)
    began = time.perf_counter()
    manifest = export_model(model, args.out, args.format, args.input_size, args.history_frames)
    names = V3_GRAPHS if isinstance(manifest, V3Manifest) else GRAPHS
    files = ", ".join(manifest.graph_path(args.out, name).name for name in names)
    height, width = manifest.input_size
    print(
        f"wrote {args.out}: {files}, taptr-export.json ({width}×{height} frames, "
        f"S = {manifest.num_tokens} tokens, C = {manifest.d_model}) in "
        f"{time.perf_counter() - began:.1f} s"
    )
    if args.check:
        parity = compare(
            model,
            args.out,
            num_frames=args.check_frames,
            num_points=args.check_points,
            repeats=args.repeats,
            threads=args.threads,
        )
        runtime = "onnxruntime" if manifest.format == "onnx" else "TorchScript"
        print(
            f"check on the {args.check_frames}-frame sample clip, {args.check_points} points: "
            f"max |Δ| positions {parity.position_error:.2e} "
            f"({parity.position_error_pixels:.2e} px), visibility logits "
            f"{parity.visibility_error:.2e}; PyTorch {parity.torch_seconds:.2f} s, "
            f"{runtime} {parity.exported_seconds:.2f} s (best of {args.repeats})"
        )
    return 0
