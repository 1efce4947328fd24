"""Runs the fuzz categories of tests/fuzz_targets.py and prints a markdown table of outcomes.

For each input category, ``--examples`` generated inputs (default 2,000, the long profile)
go through the category's reader; each outcome is counted as a clean error (a ValueError or
FileNotFoundError), a traceback (any other exception), silent wrong output (a result with
NaN or a malformed array, a limit bypassed, a reader blocked on a FIFO, or a peak RSS grown
by more than 512 MiB) or a valid result. Before that, every case of scripts/bomb_cases.py
(the worst inputs of the reviews) runs in a child process of its own under an 8 GiB
address-space cap (``prlimit --as``), which reports its peak resident memory.

Usage::

    python scripts/fuzz_report.py                    # 2,000 examples per category
    python scripts/fuzz_report.py --examples 300 -v  # fewer, and print each traceback
    python scripts/fuzz_report.py --no-fuzz          # the bomb (peak RSS) table only
"""

from __future__ import annotations

import argparse
import collections
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hypothesis import HealthCheck, given, settings  # noqa: E402

ADDRESS_SPACE = 8 * 1024**3


def fuzz(name: str, examples: int, verbose: bool) -> collections.Counter[str]:
    """Outcome counts of ``examples`` generated inputs of category ``name``."""
    from tests import fuzz_targets

    strategy, target = fuzz_targets.CATEGORIES[name]
    counts: collections.Counter[str] = collections.Counter()
    problems: list[str] = []

    @settings(
        max_examples=examples,
        deadline=None,
        database=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(strategy)
    def run(value: object) -> None:
        counts[fuzz_targets.classify(target, value, problems)] += 1

    run()
    if verbose:
        for problem in problems[:3]:
            print(f"--- {name}\n{problem}", file=sys.stderr)
    return counts


def bombs(timeout: float) -> list[tuple[str, int, str]]:
    """(case, peak RSS in bytes, outcome) of every case of scripts/bomb_cases.py.

    Each case runs in a child of its own under an 8 GiB address-space cap (``prlimit --as``),
    so each peak is that input's alone; a child still running after ``timeout`` seconds
    (a reader blocked on a FIFO) is killed and reported as hung.
    """
    script = [sys.executable, str(ROOT / "scripts" / "bomb_cases.py")]
    env = dict(os.environ, OMP_NUM_THREADS="1", HF_HUB_OFFLINE="1")
    names = subprocess.run(
        [*script, "--list"], capture_output=True, text=True, env=env, check=True
    ).stdout.splitlines()
    cap = ["prlimit", f"--as={ADDRESS_SPACE}"] if shutil.which("prlimit") else []
    rows = []
    for name in names:
        try:
            done = subprocess.run(
                [*cap, *script, name], capture_output=True, text=True, env=env, timeout=timeout
            )
        except subprocess.TimeoutExpired:
            rows.append((name, 0, f"HUNG: killed after {timeout:.0f} s"))
            continue
        line = next((x for x in done.stdout.splitlines() if x.count("\t") == 2), None)
        if line is None:
            rows.append((name, 0, f"CHILD DIED (status {done.returncode}): {done.stderr[-200:]}"))
            continue
        case, rss, outcome = line.split("\t")
        rows.append((case, int(rss), outcome))
    return rows


def _print_bombs(rows: list[tuple[str, int, str]]) -> int:
    """Prints the bomb table; returns how many cases were not refused cleanly."""
    print(f"Bombs, one child process each under prlimit --as={ADDRESS_SPACE} (8 GiB):\n")
    print("| input | peak RSS (MiB) | outcome |")
    print("|---|---:|---|")
    for name, rss, outcome in rows:
        print(f"| {name} | {rss / 2**20:.0f} | {outcome} |", flush=True)
    if rows:
        base, peak = rows[0][1], max(rss for _, rss, _ in rows)
        print(
            f"\nPeak RSS of the worst input: {peak / 2**20:.0f} MiB ({(peak - base) / 2**20:.0f} "
            f"MiB above the {base / 2**20:.0f} MiB of a child that only imports taptr and torch)"
        )
    return sum(not (o.startswith("clean") or n == "baseline") for n, _, o in rows)


def main() -> int:
    """Prints the bomb table and the fuzz table; exit status 1 if anything is not clean."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--examples", type=int, default=2000, help="inputs per category")
    parser.add_argument("--only", help="run only categories whose name contains this")
    parser.add_argument("-v", "--verbose", action="store_true", help="print tracebacks")
    parser.add_argument("--no-bombs", action="store_true", help="skip the bomb table")
    parser.add_argument("--no-fuzz", action="store_true", help="skip the fuzz table")
    parser.add_argument("--timeout", type=float, default=120, help="seconds per bomb child")
    args = parser.parse_args()
    bad = 0 if args.no_bombs else _print_bombs(bombs(args.timeout))
    if args.no_fuzz:
        return 1 if bad else 0
    from tests import fuzz_targets

    print(f"\nFuzz: {args.examples} generated inputs per category\n")
    print("| category | tried | valid | clean errors | tracebacks | silent wrong | seconds |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name in fuzz_targets.CATEGORIES:
        if args.only and args.only not in name:
            continue
        start = time.perf_counter()
        counts = fuzz(name, args.examples, args.verbose)
        tried = sum(counts.values())
        bad += counts["traceback"] + counts["silent"]
        print(
            f"| {name} | {tried} | {counts['valid']} | {counts['clean']} | "
            f"{counts['traceback']} | {counts['silent']} | {time.perf_counter() - start:.0f} |",
            flush=True,
        )
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
