"""``taptr bench``: time and memory of the reference and the fast execution, side by side."""

from __future__ import annotations

import argparse
import shlex
import sys

from taptr.cli.options import (
    add_device_argument,
    check_at_least,
    check_device,
    check_input_size,
    check_output_file,
)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    parser = subparsers.add_parser(
        "bench",
        help="measure speed, memory and FLOPs (random weights and video)",
        description="Runs each preset × points case in the reference execution (grid_sample "
        "attention, N × N point-attention masks, all frames encoded up front) and the fast one "
        "(gather attention, point attention on tracked points, frames encoded per window), each "
        "in its own process, and reports seconds per frame, a per-stage breakdown, peak memory "
        "and the agreement of their outputs.",
    )
    parser.add_argument(
        "--preset",
        nargs="+",
        default=["taptrv2"],
        help="one or more model presets, e.g. taptrv2 small (default: taptrv2)",
    )
    parser.add_argument(
        "--frames", type=int, default=24, help="frames of the random video (default 24)"
    )
    parser.add_argument(
        "--points",
        type=int,
        nargs="+",
        default=[800],
        metavar="N",
        help="one or more numbers of query points (default 800)",
    )
    parser.add_argument(
        "--size",
        type=int,
        nargs=2,
        default=[512, 512],
        metavar=("H", "W"),
        help="frame size the model sees (default 512 512)",
    )
    parser.add_argument(
        "--threads", type=int, default=2, help="CPU threads of each measured process (default 2)"
    )
    add_device_argument(parser, default="cpu")
    parser.add_argument(
        "--dtype",
        choices=["float32", "bfloat16"],
        default="float32",
        help="dtype of weights and activations (default float32)",
    )
    parser.add_argument(
        "--execution",
        choices=["both", "fast", "reference"],
        default="both",
        help="which execution to measure; both also compares their outputs (default both)",
    )
    parser.add_argument("--flops", action="store_true", help="also count FLOPs (slower)")
    parser.add_argument("--json", metavar="FILE", help="write all results to this JSON file")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Runs the cases and prints the table."""
    check_bench_arguments(args)
    from taptr.apps.benchmark import (
        BenchConfig,
        compare,
        format_table,
        machine,
        peak_flops,
        run_isolated,
        write_json,
    )

    command = "taptr " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    rows, cases = [], []
    for preset in args.preset:
        for points in args.points:
            config = BenchConfig(
                preset=preset,
                frames=args.frames,
                points=points,
                size=tuple(args.size),
                threads=args.threads,
                device=args.device,
                dtype=args.dtype,
                flops=args.flops,
            )
            if args.execution == "both":
                case = compare(config)
                rows += list(case["results"].values())
                cases.append({"preset": preset, "points": points, **case})
            else:
                chosen = args.execution
                result = run_isolated(BenchConfig(**{**config.__dict__, "execution": chosen}))
                rows.append(result)
                cases.append({"preset": preset, "points": points, "results": {chosen: result}})
    print(format_table(rows))
    for case in cases:
        agreement = case.get("agreement")
        if agreement:
            print(
                f"{case['preset']} N={case['points']}: fast/reference speed-up "
                f"{agreement['speedup']:.2f}x, peak RSS ratio {agreement['memory_ratio']:.2f}, "
                f"max |Δ position| {agreement['max_position_difference']:.2e}, "
                f"visibility decisions equal: {agreement['visibility_decisions_equal']}"
            )
    rate = peak_flops(args.threads) if args.device == "cpu" else None
    if rate:
        print(f"measured fp32 matmul peak: {rate / 1e9:.0f} GFLOP/s on {args.threads} threads")
        for row in rows:
            if row.flops:
                achieved = row.flops / (row.seconds_per_frame * row.config["frames"])
                print(
                    f"  {row.config['preset']} {row.config['execution']} "
                    f"N={row.config['points']}: "
                    f"{achieved / 1e9:.0f} GFLOP/s = {achieved / rate:.0%} of peak"
                )
    print(f"command: {command}")
    if args.json:
        write_json(
            args.json,
            {"command": command, "machine": machine(), "peak_flops": rate, "cases": cases},
        )
    return 0


def check_bench_arguments(args: argparse.Namespace) -> None:
    """Checks the options before the first measured process starts."""
    from taptr.query_checks import check_num_points

    check_input_size(args.size, "--size", minimum=32)  # tiny presets are timed on small frames
    check_at_least(args.frames, 1, "--frames")
    check_at_least(args.threads, 1, "--threads")
    for points in args.points:
        check_at_least(points, 1, "--points")
        check_num_points(points, f"--points {points}")
    if args.json:
        check_output_file(args.json, "--json")
    check_device(args.device)  # imports torch for a GPU: after the cheap checks
