"""``taptr analyze attention VIDEO``: where the decoder's cross-attention looks."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from taptr.cli.common.model_options import (
    add_model_arguments,
    check_model_arguments,
    load_predictor,
)
from taptr.cli.common.options import check_at_least, check_output_folder


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand and its analyses."""
    parser = subparsers.add_parser(
        "analyze",
        help="analyses of a model (attention)",
        description="Analyses of what a model does on a video.",
    )
    analyses = parser.add_subparsers(dest="analysis", required=True, metavar="ANALYSIS")
    attention = analyses.add_parser(
        "attention",
        help="distribution of the decoder's cross-attention weights over sampling offsets",
        description="Tracks a grid of points and records, without changing any computation, "
        "every decoder layer's cross-attention weights and the offsets of their samples "
        "from the point (pixels of the model input), on the frames after the query frame. "
        "Writes OUT/attention.json (per layer: weighted and plain sample distances, mass "
        "and share of samples per distance bin, mass per level, entropy, a 2-D histogram) "
        "and OUT/attention.png (heat maps per layer and the distance profile).",
    )
    attention.add_argument("video", help="video file or folder of images")
    attention.add_argument(
        "--grid", type=int, default=10, metavar="N", help="analyse an N×N grid (default: 10)"
    )
    attention.add_argument(
        "--query-frame", type=int, default=0, help="frame of the grid (default: 0)"
    )
    attention.add_argument(
        "--radius",
        type=float,
        default=None,
        help="half-width of the heat maps in model-input pixels (default: the 95th "
        "percentile of the sample distances)",
    )
    attention.add_argument("--out", required=True, help="output folder")
    add_model_arguments(attention)
    attention.set_defaults(func=run_attention)


def run_attention(args: argparse.Namespace) -> int:
    """Runs the attention analysis and writes the JSON and the PNG."""
    from taptr.io.video import read_video, video_info, write_image

    check_model_arguments(args)
    check_at_least(args.grid, 1, "--grid")
    check_output_folder(args.out)
    if args.radius is not None and args.radius <= 0:
        raise ValueError("--radius must be positive")
    video_info(args.video)  # a missing or unreadable video fails before torch loads
    from taptr.api.inputs import grid_queries
    from taptr.apps.attention_analysis import (
        analyze_attention,
        attention_statistics,
        draw_attention,
    )

    predictor = load_predictor(args)
    video = read_video(args.video, max_frames=args.max_frames)
    if not 0 <= args.query_frame < video.shape[0] - 1:
        raise ValueError(f"--query-frame must lie in [0, {video.shape[0] - 1}) (frames after it)")
    queries = grid_queries(args.grid, args.query_frame, video.shape[1], video.shape[2])
    records = analyze_attention(predictor, video, queries)
    statistics = attention_statistics(records, radius=args.radius)
    config = predictor.model.config
    model = str(predictor.source or args.checkpoint)  # the default model's name when none given
    report = {
        "model": model,
        "video": str(args.video),
        "num_frames": int(video.shape[0]),
        "points": int(queries.shape[0]),
        "query_frame": args.query_frame,
        "input_size": list(predictor.input_size),
        "cross_attention": getattr(config, "cross_attention", None),
        "position_update": getattr(config, "position_update", None),
        **statistics,
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "attention.json").write_text(json.dumps(report, indent=1) + "\n")
    title = f"{model} on {Path(args.video).name}: cross-attention around the point"
    write_image(out / "attention.png", draw_attention(statistics, title))

    edges = statistics["distance_edges"]
    near = edges.index(4.0)  # bins below 4 px
    print(
        f"{'layer':>5} {'entries':>8} {'w.dist':>7} {'dist':>7} {'mass<4':>7} {'samp<4':>7} "
        f"{'entropy':>7} {'max w':>6}"
    )
    for layer in statistics["layers"]:
        mass = sum(layer["mass_by_distance"][:near])
        share = sum(layer["samples_by_distance"][:near])
        print(
            f"{layer['layer']:>5} {layer['entries']:>8} "
            f"{layer['attention_weighted_distance']:>7.2f} {layer['mean_sample_distance']:>7.2f} "
            f"{mass:>7.3f} {share:>7.3f} {layer['normalised_entropy']:>7.3f} "
            f"{layer['max_weight']:>6.3f}"
        )
    print(f"wrote {out / 'attention.json'} and {out / 'attention.png'}")
    return 0
