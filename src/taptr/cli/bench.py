"""``taptr bench``: time and memory of the reference and the fast execution, side by side."""

from __future__ import annotations

import argparse
import itertools
import os
import shlex
import sys

from taptr.cli.common.options import (
    add_device_argument,
    add_frames_per_call_argument,
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
        default=None,
        metavar=("H", "W"),
        help="frame size the model sees (default: each preset's input size, 512 512 for "
        "taptrv2, 384 512 for taptrv3)",
    )
    parser.add_argument(
        "--history-frames",
        type=int,
        nargs="+",
        default=[None],
        metavar="N",
        help="TAPTRv3 presets: one or more history limits (0: the whole video; default: "
        "the model's)",
    )
    parser.add_argument(
        "--threads", type=int, default=2, help="CPU threads of each measured process (default 2)"
    )
    add_device_argument(parser, default="cpu")
    parser.add_argument(
        "--dtype",
        choices=["float32", "bfloat16", "float16"],
        nargs="+",
        default=["float32"],
        help="one or more of: float32; bfloat16 or float16 autocast on CUDA; on the CPU, "
        "bfloat16 products through oneDNN where the CPU has them natively (default float32)",
    )
    parser.add_argument(
        "--compile",
        action="store_true",
        help="torch.compile the model's heavy parts first (compilation is not timed on CUDA)",
    )
    add_frames_per_call_argument(parser)
    parser.add_argument(
        "--execution",
        choices=["both", "fast", "reference"],
        default="both",
        help="which execution to measure; both also compares their outputs (default both)",
    )
    parser.add_argument(
        "--flops",
        action="store_true",
        help="also count FLOPs (a slower second pass) and print each stage's GFLOP, time and "
        "share of this host's measured peak for its precision (float32, bfloat16, int8)",
    )
    parser.add_argument(
        "--count-ops",
        action="store_true",
        help="instead of timing, count the kernel-launching operations and host syncs each "
        "frame dispatches (in this process, with the CPU's row blocks off, as on a GPU, and on)",
    )
    add_engines_argument(parser)
    parser.add_argument("--json", metavar="FILE", help="write all results to this JSON file")
    parser.set_defaults(func=run)


def add_engines_argument(parser: argparse.ArgumentParser) -> None:
    """``--engine``, several at once: whole videos through each, side by side."""
    from taptr.types import ENGINE_CHOICES

    parser.add_argument(
        "--engine",
        nargs="+",
        choices=ENGINE_CHOICES,
        default=None,
        help="instead of the executions, time whole videos (Predictor.track, capture off, "
        "against the torch-free tracker over the preset exported once) in each engine "
        "named, in turns in one process, and print each with its time against torch's; "
        "TAPTRv3 presets (e.g. --preset taptrv3 --engine torch onnxruntime openvino)",
    )


def run(args: argparse.Namespace) -> int:
    """Runs the cases and prints the table."""
    check_bench_arguments(args)
    from taptr.apps.benchmark import format_table, machine, peak_flops, write_json

    command = "taptr " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    if args.count_ops:
        return count_ops(args, command)
    if args.engine:
        return bench_engines(args, command)
    if len(args.dtype) > 1 and args.execution == "both":
        raise ValueError("several --dtype values compare one --execution (fast or reference)")
    rows, cases = _run_cases(args)
    print(format_table(rows))
    _print_growth(rows)
    _print_comparisons(cases, args.dtype[0])
    peaks = _print_roofline(rows, args) if args.flops else None
    if peaks is not None:
        rate = peaks["float32"]
    else:
        rate = peak_flops(args.threads) if args.device == "cpu" else None
        if rate:
            print(f"measured fp32 matmul peak: {rate / 1e9:.0f} GFLOP/s on {args.threads} threads")
    if rate:
        _print_flops(rows, rate)
    print(f"command: {command}")
    if args.json:
        record = {"command": command, "machine": machine(), "peak_flops": rate, "cases": cases}
        write_json(args.json, record | {"peaks": peaks})
    return 0


def _run_cases(args: argparse.Namespace) -> tuple[list, list[dict]]:
    """Runs every (preset, points, history) case; returns the table's rows and the cases."""
    from taptr.apps.benchmark import BenchConfig, compare, compare_types, run_isolated
    from taptr.config import get_config

    rows: list = []
    cases: list[dict] = []
    cases_to_run = [
        (preset, points, history)
        for preset in args.preset
        for points in args.points
        # history limits are TAPTRv3's: the other presets run once
        for history in (args.history_frames if get_config(preset).version == 3 else [None])
    ]
    for preset, points, history in cases_to_run:
        model = get_config(preset)
        height, width = args.size or model.input_size
        config = BenchConfig(
            preset=preset,
            frames=args.frames,
            points=points,
            size=(height, width),
            threads=args.threads,
            device=args.device,
            dtype=args.dtype[0],
            flops=args.flops,
            history_frames=history,
            compile=args.compile,
            frames_per_call=args.frames_per_call,
        )
        if args.execution == "both":
            case = compare(config)
        elif len(args.dtype) > 1:
            chosen = BenchConfig(**{**config.__dict__, "execution": args.execution})
            case = compare_types(chosen, args.dtype)
        else:
            chosen = BenchConfig(**{**config.__dict__, "execution": args.execution})
            case = {"results": {args.execution: run_isolated(chosen)}}
        rows += list(case["results"].values())
        cases.append({"preset": preset, "points": points, **case})
    return rows, cases


def _print_growth(rows: list) -> None:
    """Seconds per frame at frame 24 and at the last frame, for runs longer than 24."""
    from taptr.apps.benchmark import seconds_per_frame_at

    for row in rows:
        at_24, at_end = (seconds_per_frame_at(row, f) for f in (24, row.config["frames"]))
        if at_24 is not None and at_end is not None and row.config["frames"] > 24:
            print(
                f"{row.config['preset']} {row.config['execution']} N={row.config['points']} "
                f"history {row.config['history_frames']}: {at_24:.3f} s/frame at frame 24, "
                f"{at_end:.3f} at frame {row.config['frames']}"
            )


def _print_comparisons(cases: list[dict], dtype: str) -> None:
    """Each case's other types against ``dtype``, and fast against reference."""
    for case in cases:
        for other, change in case.get(f"against_{dtype}", {}).items():
            print(
                f"{case['preset']} N={case['points']}: {other} {change['speedup']:.2f}x "
                f"{dtype}, peak RSS ratio {change['memory_ratio']:.2f}, positions moved "
                f"max {change['max_position_change_px']:.3f} px, median "
                f"{change['median_position_change_px']:.4f} px, visibility decisions flipped "
                f"{change['visibility_flips']} of {change['visibility_decisions']}"
            )
        agreement = case.get("agreement")
        if agreement:
            print(
                f"{case['preset']} N={case['points']}: fast/reference speed-up "
                f"{agreement['speedup']:.2f}x, peak RSS ratio {agreement['memory_ratio']:.2f}, "
                f"max |Δ position| {agreement['max_position_difference']:.2e}, "
                f"visibility decisions equal: {agreement['visibility_decisions_equal']}"
            )


def _print_flops(rows: list, rate: float) -> None:
    """Each row's whole run against the float32 peak ``rate`` (FLOP/s)."""
    for row in rows:
        if row.flops:
            achieved = row.flops / (row.seconds_per_frame * row.config["frames"])
            print(
                f"  {row.config['preset']} {row.config['execution']} "
                f"N={row.config['points']}, whole run: "
                f"{achieved / 1e9:.0f} GFLOP/s = {achieved / rate:.0%} of the float32 peak"
            )


def _print_roofline(rows: list, args: argparse.Namespace) -> dict[str, float | None]:
    """``--flops``: each stage's GFLOP, time and share of this host's peak for its precision.

    Returns the peaks (FLOP/s; None where not measured: not on a CPU, or not here).
    """
    from taptr.apps.roofline import PRECISIONS, format_peaks, format_roofline, peak_rates

    if args.device == "cpu":
        peaks = peak_rates(args.threads)
        print(format_peaks(peaks, args.threads))
    else:
        peaks = dict.fromkeys(PRECISIONS)
    print(format_roofline(rows, peaks))
    return peaks


def count_ops(args: argparse.Namespace, command: str) -> int:
    """``--count-ops``: operations and host syncs per frame of each preset, printed."""
    import torch

    from taptr.apps.benchmark import machine, write_json
    from taptr.config import get_config
    from taptr.model.build import build_model
    from taptr.runtime.op_count import as_on_accelerator, count_frame_ops

    torch.set_num_threads(args.threads)
    print("kernel-launching ATen operations and host syncs per frame, after the first step")
    print(f"{'preset':12} {'size':>9} {'N':>6} {'row blocks':>10} {'ops/frame':>10} {'syncs':>6}")
    counts = []
    for preset in args.preset:
        config = get_config(preset)
        size = tuple(args.size or config.input_size)
        frames = 6 if config.version == 3 else config.window_size + 2 * config.window_stride
        torch.manual_seed(0)
        model = build_model(preset).eval().to(args.device)
        on_cpu = model.execution  # row blocks as the CPU takes them
        for points, blocks in itertools.product(args.points, (False, True)):
            if blocks:
                model.set_execution(on_cpu)
            else:
                as_on_accelerator(model)
            count = count_frame_ops(model, size, points, frames)
            counts.append(
                {"preset": preset, "size": size, "points": points, "row_blocks": blocks}
                | count._asdict()
            )
            shown = "on" if blocks else "off"
            print(
                f"{preset:12} {size[0]:>4}x{size[1]:<4} {points:>6} {shown:>10} "
                f"{count.per_frame:10.1f} {count.syncs_per_frame:6.2f}"
            )
            if not blocks:
                top = ", ".join(f"{n} {c:.0f}" for n, c in list(count.by_name.items())[:8])
                print(f"{'':12} most frequent: {top}")
    print(f"command: {command}")
    if args.json:
        write_json(args.json, {"command": command, "machine": machine(), "op_counts": counts})
    return 0


def bench_engines(args: argparse.Namespace, command: str) -> int:
    """``--engine``: each engine's seconds per frame on whole videos, printed."""
    from taptr.apps.benchmark import machine, write_json
    from taptr.apps.engine_bench import EngineCase, engine_lines, run_engines
    from taptr.config import get_config

    results = []
    for preset, points in itertools.product(args.preset, args.points):
        size = tuple(args.size or get_config(preset).input_size)
        engines = tuple(dict.fromkeys(args.engine))
        case = EngineCase(preset, args.frames, points, size, args.threads, engines)
        seconds = run_engines(case)
        print("\n".join(engine_lines(case, seconds)), flush=True)
        results.append({"preset": preset, "points": points, "seconds_per_frame": seconds})
    print(f"command: {command}")
    if args.json:
        write_json(args.json, {"command": command, "machine": machine(), "engines": results})
    return 0


def check_bench_arguments(args: argparse.Namespace) -> None:
    """Checks the options before the first measured process starts."""
    from taptr.config import PRESETS
    from taptr.task.query_checks import check_num_points

    if args.size is not None:
        check_input_size(args.size, "--size", minimum=32)  # tiny presets: small frames
    unknown = [preset for preset in args.preset if preset not in PRESETS]
    if unknown:
        raise ValueError(f"unknown preset {unknown[0]!r}; known: {', '.join(PRESETS)}")
    for history in args.history_frames:
        if history is not None and (history < 0 or history == 1):
            raise ValueError("--history-frames must be 0 (the whole video) or at least 2")
    if "float16" in args.dtype and args.device == "cpu":
        raise ValueError("--dtype float16 is CUDA autocast; on the CPU use bfloat16")
    if "bfloat16" in args.dtype and args.device == "cpu":
        from taptr.model.ops.dense import native_bfloat16

        if not native_bfloat16():
            raise ValueError(
                "--dtype bfloat16: this CPU has no native bfloat16 (AVX512-BF16 or AMX)"
            )
    check_at_least(args.frames, 1, "--frames")
    check_at_least(args.threads, 1, "--threads")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    if cores and args.threads > cores:
        raise ValueError(f"--threads {args.threads}: this process may use {cores} CPU threads")
    for points in args.points:
        check_at_least(points, 1, "--points")
        check_num_points(points, f"--points {points}")
    if args.json:
        check_output_file(args.json, "--json")
    if args.engine:
        check_engine_case(args)
    check_device(args.device)  # imports torch for a GPU: after the cheap checks
    check_bench_memory(args)


def check_engine_case(args: argparse.Namespace) -> None:
    """Refuses what ``--engine`` cannot compare: other presets, other devices and types."""
    from taptr.config import get_config

    others = [preset for preset in args.preset if get_config(preset).version != 3]
    if others:
        raise ValueError(f"--engine compares TAPTRv3 presets; {others[0]} is not one")
    if args.device != "cpu" or args.dtype != ["float32"] or args.count_ops:
        raise ValueError("--engine compares float32 on the CPU (no --device, --dtype, --count-ops)")


def check_bench_memory(args: argparse.Namespace) -> None:
    """Refuses, before any worker starts, a case whose estimated peak exceeds the budget.

    Each case holds its random video (uint8) and, in the reference execution, every frame
    encoded up front (4 · S · C bytes a frame) besides a tracking run's memory.
    """
    from taptr.config import get_config
    from taptr.memory_estimate import Estimate, check_memory, encoder_tokens, estimate_tracking

    for preset in args.preset:
        config = get_config(preset)
        height, width = args.size or config.input_size
        knobs = f"use fewer --frames, fewer --points or a smaller --size (now {height} {width})"
        histories = args.history_frames if config.version == 3 else [None]
        for points, history in itertools.product(args.points, histories):
            estimate = estimate_tracking(
                config,
                input_size=(height, width),
                num_frames=args.frames,
                num_points=points,
                frame_size=(height, width),
                whole_video=True,
                history_frames=history,
            )
            if args.execution != "fast":
                encoded = 4 * encoder_tokens(height, width) * config.d_model * args.frames
                estimate = Estimate({**estimate.parts, "encoded video": encoded})
            what = f"{preset} with {points:,} points through {args.frames:,} frames"
            check_memory(estimate, what, knobs, args.device)
