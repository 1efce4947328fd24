"""``taptr demo``: serve the web demo (Gradio) on this machine.

Gradio is an optional dependency (the ``demo`` extra) and is imported only when the command
runs, so ``taptr --help`` works without it.
"""

from __future__ import annotations

import argparse
import importlib.util
import ipaddress
import sys

from taptr.cli.common.model_options import (
    add_model_arguments,
    check_model_arguments,
    load_predictor,
)
from taptr.messages import install_line


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    from taptr.apps.demo.settings import DEFAULT_HOST, DEFAULT_PORT, Limits

    defaults = Limits()
    parser = subparsers.add_parser(
        "demo",
        help="start the web demo (needs the demo extra: Gradio)",
        description="Serves a Gradio page for tracking clicked points, painted regions or grids "
        "and for editing videos. Uploads and outputs stay in a temporary folder that is removed "
        "on exit (or by the next start, if the server was killed). Stop it with Ctrl-C.",
    )
    parser.add_argument(
        "--host", default=DEFAULT_HOST, help=f"interface to bind (default {DEFAULT_HOST})"
    )
    parser.add_argument(
        "--port", type=int, default=DEFAULT_PORT, help=f"TCP port (default {DEFAULT_PORT})"
    )
    parser.add_argument(
        "--max-side",
        type=int,
        default=defaults.max_side,
        help=f"refuse videos larger than this many pixels on the longer side "
        f"(default {defaults.max_side})",
    )
    parser.add_argument(
        "--max-points",
        type=int,
        default=defaults.max_points,
        help=f"most points one run may track (default {defaults.max_points})",
    )
    parser.add_argument(
        "--max-disk-gb",
        type=float,
        default=defaults.max_disk_bytes / 2**30,
        help="most disk space uploads and outputs may take together, in GiB; beyond it "
        f"uploads and runs are refused until old runs expire (default "
        f"{defaults.max_disk_bytes / 2**30:g})",
    )
    add_model_arguments(parser, max_frames=defaults.max_frames)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Loads the model and serves the demo until interrupted."""
    if importlib.util.find_spec("gradio") is None:
        hint = install_line("demo")
        print(f"taptr demo: error: the demo needs Gradio: {hint}", file=sys.stderr)
        return 2
    from taptr.apps.demo.settings import Limits

    check_model_arguments(args)
    if not 1 <= args.port <= 65535:  # Gradio takes 0 and then fails to reach itself
        raise ValueError(f"--port must lie in [1, 65535], got {args.port}")
    if not args.max_disk_gb > 0:
        raise ValueError(f"--max-disk-gb must be positive, got {args.max_disk_gb}")
    limits = Limits(
        max_frames=args.max_frames,
        max_side=args.max_side,
        max_points=args.max_points,
        max_disk_bytes=int(args.max_disk_gb * 2**30),
    )
    if not _is_loopback(args.host):
        print(
            f"taptr demo: warning: binding {args.host} puts the demo, which has no login, "
            "on your network",
            file=sys.stderr,
        )
    from taptr.apps.demo.launch import private_workspace, serve  # Gradio: after the checks

    predictor = load_predictor(args)
    model_name = predictor.source or "custom"
    with private_workspace() as workspace:
        print(
            f"taptr demo: http://{args.host}:{args.port} (model {model_name}; temporary files in "
            f"{workspace}, removed on exit; Ctrl-C to stop)",
            flush=True,
        )
        try:
            serve(
                predictor,
                workspace,
                host=args.host,
                port=args.port,
                limits=limits,
                model_name=model_name,
            )
        except OSError as error:
            raise ValueError(f"cannot serve on {args.host}:{args.port}: {error}") from None
    return 0


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
