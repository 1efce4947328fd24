"""The benchmark cases behind docs/BENCHMARKS.md, by name: ``python benchmarks/suite.py CASE``.

Each case is one or more ``taptr bench`` commands (random weights and video, every speed-up
against the reference execution in the same command). Results go to
``benchmarks/results/CASE*.json`` (or ``--out``) and the printed tables go to the terminal;
``--dry-run`` lists the commands only.

Cases:
    headline   paper preset, 512×512, 24 frames, 800 points: reference vs fast, FLOPs.
    versions   TAPTRv2 vs TAPTR v1 at 800 and 5000 points (the paper's efficiency table).
    length     memory flat in video length: fast execution at 24 and 300 frames.
    points     10,000 vs 1,000 points at 256×256 (fast execution; the reference execution's
               N×N masks and all-frame features are the baseline at 1,000 points).
    gpu        800 and 5000 points on CUDA: float32, bfloat16 and float16 autocast, and
               torch.compile in float32 and bfloat16 (each case warmed up untimed first).
    gpu-v3     TAPTRv3 ResNet-18 and ResNet-50 on CUDA, 800 and 5000 points, float32 and
               bfloat16 autocast.
    v3         TAPTRv3 ResNet-18 (384×512) and ResNet-50 (512×512) next to TAPTRv2 (512²),
               24 frames, 800 points, reference vs fast.
    v3-long    TAPTRv3-R18 fast over 1,000 frames, 800 points: time per frame at frame 24 and
               at frame 1,000 of one run (the long-temporal attention grows with the video).
    v3-memory  TAPTRv3-R18 fast over 1,000 frames at 100 and 800 points, the whole history
               and a 24-frame history: peak memory.
    smoke      a tiny case that runs in seconds (what CI runs through the test suite).
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"

CASES: dict[str, list[list[str]]] = {
    "headline": [["--preset", "taptrv2", "--frames", "24", "--points", "800", "--flops"]],
    "versions": [
        ["--preset", "taptrv2", "taptrv1", "--frames", "24", "--points", "800", "5000",
         "--execution", "fast", "--flops"],
    ],
    "length": [
        ["--preset", "taptrv2", "--frames", "24", "--points", "800", "--execution", "fast"],
        ["--preset", "taptrv2", "--frames", "300", "--points", "800", "--execution", "fast"],
    ],
    "points": [
        ["--preset", "taptrv2", "--frames", "24", "--size", "256", "256", "--points", "1000"],
        ["--preset", "taptrv2", "--frames", "24", "--size", "256", "256", "--points", "10000",
         "--execution", "fast"],
    ],
    "gpu": [
        ["--preset", "taptrv2", "--frames", "24", "--points", "800", "5000", "--device", "cuda",
         "--execution", "fast", "--dtype", dtype, *extra]
        for dtype, extra in (("float32", []), ("bfloat16", []), ("float16", []),
                             ("float32", ["--compile"]), ("bfloat16", ["--compile"]))
    ],
    "gpu-v3": [
        ["--preset", "taptrv3", "taptrv3-r50", "--frames", "24", "--points", "800", "5000",
         "--device", "cuda", "--execution", "fast", "--dtype", dtype]
        for dtype in ("float32", "bfloat16")
    ],
    "v3": [["--preset", "taptrv3", "taptrv3-r50", "taptrv2", "--frames", "24", "--points", "800"]],
    "v3-long": [
        ["--preset", "taptrv3", "--frames", "1000", "--points", "800", "--execution", "fast"],
    ],
    "v3-memory": [
        ["--preset", "taptrv3", "--frames", "1000", "--points", "100", "800", "--execution",
         "fast", "--history-frames", "0", "24"],
    ],
    "smoke": [
        ["--preset", "tiny", "--frames", "9", "--points", "5", "--size", "32", "48", "--threads",
         "1"]
    ],
}  # fmt: skip


def commands(case: str, threads: int | None, out_dir: Path = RESULTS) -> list[list[str]]:
    """The ``taptr bench`` argument lists of a case, each writing its own JSON file."""
    runs = []
    for index, arguments in enumerate(CASES[case]):
        extra = ["--threads", str(threads)] if threads and "--threads" not in arguments else []
        out = out_dir / f"{case}{'' if len(CASES[case]) == 1 else f'-{index}'}.json"
        runs.append(["taptr", "bench", *arguments, *extra, "--json", str(out)])
    return runs


def main(argv: list[str] | None = None) -> int:
    """Runs (or lists) the commands of the chosen cases; returns the first failing status."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cases", nargs="+", choices=sorted(CASES))
    parser.add_argument("--threads", type=int, help="threads for every command (default 2)")
    parser.add_argument("--out", type=Path, default=RESULTS, help="folder for the JSON files")
    parser.add_argument("--dry-run", action="store_true", help="print the commands only")
    args = parser.parse_args(argv)
    for case in args.cases:
        for command in commands(case, args.threads, args.out):
            print("$", shlex.join(command), flush=True)
            if args.dry_run:
                continue
            args.out.mkdir(parents=True, exist_ok=True)
            status = subprocess.run(command, check=False).returncode
            if status:
                return status
    return 0


if __name__ == "__main__":
    sys.exit(main())
