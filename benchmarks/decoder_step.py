"""TAPTRv3's per-frame decoder step with the value table against values projected after sampling.

Frames are encoded once beforehand; each case then decodes them all (the step of
`taptr.model.v3.per_frame`, eager) at the point counts the predictor really feeds the
model for the given user queries (support points included: `Predictor.model_points`),
every point starting on frame 0 (which is therefore not decoded: seconds per frame are
per decoded frame, ``--frames`` − 1 of them). The cases are the fast execution as it is and the fast
execution with ``values_after_sampling`` off (every token projected into the value
table, as before), run in turns (one of each, the order alternating) on the same
memory and points; the best of the turns is kept, because on a shared machine only
times measured together compare. Also reported: the largest position difference between
the two, and the load average before and after.

With ``--against SRC`` the cases are instead this source's fast execution and another
source tree's (``SRC`` goes first on ``PYTHONPATH``: the ``src`` folder of a checkout of
an older commit, e.g. from ``git worktree add``), each turn running each in a fresh
process, the order alternating: code that has changed, not only the execution's fields.

    python benchmarks/decoder_step.py                          # TAPTRv3-R18, 384 × 512
    python benchmarks/decoder_step.py --against /tmp/base/src  # against an older commit
    python benchmarks/decoder_step.py --preset tiny-v3 --size 48 64 --queries 3 --frames 3
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from taptr.apps.benchmark import machine, write_json
from taptr.model.build import build_model
from taptr.model.taptr import normalize_frames
from taptr.model.trajectory import QuerySet
from taptr.model.v3.per_frame import run_frames
from taptr.runtime.frames import PrecomputedFrames

OFF = {"values_after_sampling": False}
"""The fast execution's fields as before values were projected after sampling."""


def model_points(model: torch.nn.Module, queries: int) -> int:
    """The points the predictor hands the model for ``queries`` user points."""
    from taptr.api.predictor import Predictor

    return Predictor(model, device="cpu", capture="off").model_points(queries)


def decoder_run(model, memory, points: int, seed: int) -> Callable[[], torch.Tensor]:
    """Decodes every encoded frame for ``points`` random points; returns the positions."""
    frames = memory.memory.shape[1]
    generator = torch.Generator().manual_seed(seed)
    queries = QuerySet(
        torch.zeros(1, points, dtype=torch.long),
        torch.rand(1, points, 2, generator=generator) * 0.9 + 0.05,
        torch.ones(1, points, dtype=torch.bool),
    )

    def run() -> torch.Tensor:
        with torch.no_grad():
            out = run_frames(model, queries, frames, PrecomputedFrames(memory), torch.float32)
        return out.positions

    return run


def in_turns(model, runs: dict[str, Any], turns: int) -> dict[str, Any]:
    """Each (execution, run) once untimed, then ``turns`` alternating rounds; best seconds."""
    outputs, best = {}, dict.fromkeys(runs, float("inf"))
    for name, (execution, run) in runs.items():
        model.set_execution(execution)
        outputs[name] = run()
    names = list(runs)
    for turn in range(turns):
        for name in names if turn % 2 == 0 else names[::-1]:
            execution, run = runs[name]
            model.set_execution(execution)
            start = time.perf_counter()
            outputs[name] = run()
            best[name] = min(best[name], time.perf_counter() - start)
    return {"seconds": best, "outputs": outputs}


def encoded(args: argparse.Namespace) -> tuple[torch.nn.Module, Any]:
    """The seeded model at ``--size`` and its memory of ``--frames`` random frames."""
    from taptr.config import get_config

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = build_model(get_config(args.preset).replace(input_size=tuple(args.size))).eval()
    video = torch.rand(1, args.frames, 3, *args.size, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        memory = model.encode(normalize_frames(video))
    return model, memory


def one_case(args: argparse.Namespace, queries: int, out: Path) -> None:
    """``--child``: this source's fast step, once untimed then timed; seconds and positions."""
    model, memory = encoded(args)
    points = model_points(model, queries)
    run = decoder_run(model, memory, points, seed=queries)
    measured = in_turns(model, {"fast": (model.execution, run)}, 1)
    torch.save(measured["outputs"]["fast"], out)
    print(json.dumps({"seconds": measured["seconds"]["fast"], "model_points": points}))


def against(args: argparse.Namespace, queries: int) -> dict[str, Any]:
    """``--against``: the baseline source and this one, a fresh process each per turn."""
    import subprocess
    import tempfile

    here = str(Path(__file__).resolve().parents[1] / "src")
    sources = {"baseline": str(Path(args.against).resolve()), "fast": here}
    best, outputs, points = dict.fromkeys(sources, float("inf")), {}, 0
    options = ["--preset", args.preset, "--frames", str(args.frames), "--threads"]
    options += [str(args.threads), "--size", *map(str, args.size), "--queries", str(queries)]
    with tempfile.TemporaryDirectory() as scratch:
        names = list(sources)
        for turn in range(args.turns):
            for name in names if turn % 2 == 0 else names[::-1]:
                out = Path(scratch) / f"{name}.pt"
                env = {**os.environ, "PYTHONPATH": sources[name]}
                command = [sys.executable, __file__, *options, "--child", str(out)]
                done = subprocess.run(command, env=env, capture_output=True, text=True, check=True)
                measured = json.loads(done.stdout.strip().splitlines()[-1])
                best[name] = min(best[name], measured["seconds"])
                points = measured["model_points"]
                outputs[name] = torch.load(out)
    seconds = {name: s / (args.frames - 1) for name, s in best.items()}
    difference = (outputs["fast"] - outputs["baseline"]).abs().max()
    return {
        "model_points": points,
        "seconds_per_frame": seconds,
        "fast_over_baseline": seconds["fast"] / seconds["baseline"],
        "max_position_difference": float(difference),
    }


def toggled(args: argparse.Namespace, model, memory, queries: int) -> dict[str, Any]:
    """In this process: the fast execution with its value table (`OFF`) and without."""
    fast = model.execution
    before = dataclasses.replace(fast, **OFF)
    points = model_points(model, queries)
    run = decoder_run(model, memory, points, seed=queries)
    measured = in_turns(model, {"full_tables": (before, run), "fast": (fast, run)}, args.turns)
    model.set_execution(fast)
    seconds = {name: s / (args.frames - 1) for name, s in measured["seconds"].items()}
    outputs = measured["outputs"]
    return {
        "model_points": points,
        "seconds_per_frame": seconds,
        "fast_over_full_tables": seconds["fast"] / seconds["full_tables"],
        "max_position_difference": float((outputs["fast"] - outputs["full_tables"]).abs().max()),
    }


def main(argv: list[str] | None = None) -> int:
    """Runs both cases at every point count; prints and optionally writes one JSON object."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="taptrv3")
    parser.add_argument("--size", type=int, nargs=2, default=(384, 512))
    parser.add_argument(
        "--frames", type=int, default=6, help="frames per run; the first only starts the points"
    )
    parser.add_argument("--queries", type=int, nargs="+", default=[100, 800])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--turns", type=int, default=5)
    parser.add_argument("--against", help="a source folder to compare with (module docstring)")
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args(argv)
    if args.frames < 2:
        parser.error("--frames must be at least 2 (the first only starts the points)")
    if args.child:
        one_case(args, args.queries[0], args.child)
        return 0
    load = os.getloadavg()
    if args.against:
        results = {str(queries): against(args, queries) for queries in args.queries}
    else:
        model, memory = encoded(args)
        results = {str(q): toggled(args, model, memory, q) for q in args.queries}
    report = {
        "command": " ".join(["python", "benchmarks/decoder_step.py", *(argv or sys.argv[1:])]),
        "machine": machine(),
        "threads": args.threads,
        "load_average_before_after": [load[0], os.getloadavg()[0]],
        "queries": results,
    }
    print(json.dumps(report, indent=1))
    if args.json:
        write_json(args.json, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
