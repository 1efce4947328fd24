"""Runs the fuzz categories of tests/fuzz_targets.py and prints a markdown table of outcomes.

For each input category, ``--examples`` generated inputs (default 2,000, the long profile)
go through the category's reader; each outcome is counted as a clean error (a ValueError or
FileNotFoundError), a traceback (any other exception), silent wrong output (a result with
NaN or a malformed array) or a valid result. Then every bomb of tests/bombs.py runs in one
child process under an 8 GiB address-space cap (``prlimit --as``), which reports its peak
resident memory.

Usage::

    python scripts/fuzz_report.py                    # 2,000 examples per category
    python scripts/fuzz_report.py --examples 300 -v  # fewer, and print each traceback
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

BOMB_SCRIPT = r"""
import pickle, resource, sys, tempfile, warnings
from pathlib import Path
import numpy as np, torch
sys.path.insert(0, sys.argv[1])
from tests import bombs
from taptr.checkpoint import load_checkpoint
from taptr.data.kubric import read_sequence, write_sequence
from taptr.data.tapvid import iter_tapvid
from taptr.types import TrackingSample
from taptr.io.video import read_video

def rss():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024

def frames_pickle(path, frame, count):
    item = {"video": [frame] * count, "points": np.full((1, count, 2), 0.5),
            "occluded": np.zeros((1, count), bool)}
    path.write_bytes(pickle.dumps({"bomb": item}, protocol=4))
    return path

def tapvid(path):
    for pending in iter_tapvid("davis", path):
        pending.load()

folder = Path(tempfile.mkdtemp())
cases = {}
for name, data in bombs.pickle_bombs().items():
    (folder / f"{name}.pkl").write_bytes(data)
    cases[f"pickle {name}"] = (lambda p: lambda: tapvid(p))(folder / f"{name}.pkl")
cases["pickle 20,000 frames"] = lambda: tapvid(
    frames_pickle(folder / "f.pkl", bombs.png_bytes(256, 256), 20_000))
cases["pickle PNG frames → 4.6 GB"] = lambda: tapvid(
    frames_pickle(folder / "g.pkl", bombs.png_bytes(4096, 4096), 92))
cases["pickle PNG decompression bomb"] = lambda: tapvid(
    frames_pickle(folder / "h.pkl", bombs.png_bomb(), 2))
sample = TrackingSample(np.zeros((2, 8, 8, 3), np.uint8), np.ones((2, 1, 2), np.float32),
                        np.ones((2, 1), bool))
write_sequence(folder / "k" / "0000", sample)
bombs.npy_header_bomb(folder / "k" / "0000" / "0000.npy")
cases["npy header 7.28 TiB"] = lambda: read_sequence(folder / "k" / "0000")
(folder / "v").mkdir()
(folder / "v" / "0.png").write_bytes(bombs.png_bomb())
cases["frame folder PNG bomb"] = lambda: read_video(folder / "v")
GIB = bombs.GIB
cases["pth bytearray(12 GiB)"] = lambda: load_checkpoint(
    bombs.call_checkpoint(folder / "a.pth", bytearray, 12 * GIB))
cases["pth FloatTensor(3 Gi)"] = lambda: load_checkpoint(
    bombs.call_checkpoint(folder / "b.pth", torch.FloatTensor, 3 * GIB))
cases["pth zip storage 12 GiB"] = lambda: load_checkpoint(bombs.torch_zip(
    folder / "c.pth", {"w": bombs.tensor_ref("0", 3 * GIB)},
    {"0": (torch.FloatStorage, 3 * GIB, bytes(12))}))
cases["pth legacy storage 12 GiB"] = lambda: load_checkpoint(
    bombs.legacy_checkpoint(folder / "d.pth", 3 * GIB))
print(f"baseline\t{rss()}\tok", flush=True)
for name, run in cases.items():
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            run()
        outcome = "LOADED"
    except (ValueError, FileNotFoundError) as error:
        outcome = "clean: " + str(error).replace(str(folder), "<tmp>")[:110]
    except BaseException as error:
        outcome = f"TRACEBACK {type(error).__name__}: {error}"[:140]
    print(f"{name}\t{rss()}\t{outcome}", flush=True)
"""


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


def bombs() -> list[tuple[str, int, str]]:
    """(bomb, peak RSS in bytes after it, outcome) for every bomb, in one capped child."""
    command = [sys.executable, "-c", BOMB_SCRIPT, str(ROOT)]
    if shutil.which("prlimit"):
        command = ["prlimit", f"--as={ADDRESS_SPACE}", *command]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    done = subprocess.run(command, capture_output=True, text=True, env=env, check=False)
    rows = [line.split("\t") for line in done.stdout.splitlines() if line.count("\t") == 2]
    if done.returncode:
        rows.append(("(child exited)", "0", f"status {done.returncode}: {done.stderr[-300:]}"))
    return [(name, int(rss), outcome) for name, rss, outcome in rows]


def main() -> int:
    """Prints the bomb table and the fuzz table; exit status 1 if anything is not clean."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--examples", type=int, default=2000, help="inputs per category")
    parser.add_argument("--only", help="run only categories whose name contains this")
    parser.add_argument("-v", "--verbose", action="store_true", help="print tracebacks")
    args = parser.parse_args()
    bad = 0
    # bombs first, while this process is small: a child's peak RSS starts at its parent's
    rows = bombs()
    print(f"Bombs, one child process under prlimit --as={ADDRESS_SPACE} (8 GiB):\n")
    print("| bomb | peak RSS so far (MiB) | outcome |")
    print("|---|---:|---|")
    for name, rss, outcome in rows:
        print(f"| {name} | {rss / 2**20:.0f} | {outcome} |")
        bad += not (outcome.startswith("clean") or name == "baseline")
    if rows:
        base, peak = rows[0][1], max(rss for _, rss, _ in rows)
        print(
            f"\nPeak RSS of the worst bomb: {peak / 2**20:.0f} MiB ({(peak - base) / 2**20:.0f} "
            f"MiB above the {base / 2**20:.0f} MiB after importing taptr and torch)"
        )
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
