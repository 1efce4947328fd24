"""The quick start on a machine that other work shares: thread counts and wait policies.

Starts ``--busy`` processes that keep the cores busy (``--kind python``: a loop each, one
core; ``--kind torch``: PyTorch products on every core, OpenMP's default waits, as another
model or a test run would), then runs the README's quick
start (``taptr track sample.mp4 --grid 8``) once per setting, the settings interleaved
over ``--turns`` turns, and prints each setting's best and median seconds and its ratio
to the best setting at the same load. The settings: taptr's default (no variables; the
command chooses), and each thread count with OpenMP's default and passive wait policies.

``python benchmarks/shared_machine.py --busy 2 --kind torch --turns 3 [--json FILE]``
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from taptr.apps.benchmark import machine

SETTINGS: dict[str, dict[str, str]] = {
    "taptr default": {},
    "2 threads, OpenMP default wait": {"OMP_NUM_THREADS": "2", "OMP_WAIT_POLICY": ""},
    "2 threads, passive wait": {"OMP_NUM_THREADS": "2", "OMP_WAIT_POLICY": "PASSIVE"},
    "1 thread, OpenMP default wait": {"OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": ""},
    "1 thread, passive wait": {"OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE"},
}


def spin() -> None:
    """Keeps one core busy until killed."""
    while True:
        pass


def multiply() -> None:
    """Keeps every core busy with PyTorch products (its default threads and waits)."""
    os.environ.pop("OMP_WAIT_POLICY", None)
    os.environ.pop("OMP_NUM_THREADS", None)
    import torch

    a = torch.randn(384, 384)
    while True:
        a = torch.tanh(a @ a)


def quick_start(folder: Path, overrides: dict[str, str]) -> float:
    """Seconds of ``taptr track sample.mp4 --grid 8`` with the environment ``overrides``."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "OMP_WAIT_POLICY")}
    env.update(overrides)
    command = ["taptr", "track", str(folder / "sample.mp4"), "--grid", "8", "--out"]
    start = time.perf_counter()
    subprocess.run([*command, str(folder / "out")], env=env, check=True, capture_output=True)
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    """Prints (and writes, if asked) each setting's seconds at the load asked."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--busy", type=int, default=2, help="busy processes (default 2)")
    parser.add_argument("--kind", choices=("python", "torch"), default="torch")
    parser.add_argument("--turns", type=int, default=3)
    parser.add_argument("--json", help="write the results to this file")
    args = parser.parse_args(argv)
    work = spin if args.kind == "python" else multiply
    context = multiprocessing.get_context("spawn")  # no OpenMP state inherited
    spinners = [context.Process(target=work, daemon=True) for _ in range(args.busy)]
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        subprocess.run(["taptr", "sample-video", str(folder / "sample.mp4")], check=True)
        quick_start(folder, {})  # the first run remembers its measured choices
        for spinner in spinners:
            spinner.start()
        try:
            seconds: dict[str, list[float]] = {name: [] for name in SETTINGS}
            for _ in range(args.turns):
                for name, overrides in SETTINGS.items():
                    seconds[name].append(quick_start(folder, overrides))
                    print(f"{name}: {seconds[name][-1]:.1f} s", file=sys.stderr)
        finally:
            for spinner in spinners:
                spinner.kill()
    best = min(min(values) for values in seconds.values())
    print(f"quick start beside {args.busy} busy {args.kind} process(es), {os.cpu_count()} cores:")
    for name, values in seconds.items():
        print(
            f"  {name:32s} best {min(values):6.1f} s  median {statistics.median(values):6.1f} s"
            f"  {min(values) / best:4.2f}x the best"
        )
    if args.json:
        record = {"machine": machine(), "args": vars(args), "seconds": seconds}
        Path(args.json).write_text(json.dumps(record, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
