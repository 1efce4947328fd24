"""The evaluation report: ``results.json``, ``videos.csv`` and the console table.

``results.json`` holds the dataset, mode, protocol and tracker, the resolved config, package
versions, the git commit (null outside a git checkout), one entry per video (name, points,
frames, every metric as a fraction, seconds) and the mean over videos under tapnet's metric
names. Metrics without a value (nothing scored) are written as null.
"""

from __future__ import annotations

import csv
import importlib.metadata
import json
import math
import os
import platform
import subprocess
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from taptr.eval.metrics import METRIC_NAMES, mean_over_videos
from taptr.eval.protocols import VideoResult
from taptr.io.atomic import atomic_path

RESULTS_FILE = "results.json"
TABLE_FILE = "videos.csv"
PACKAGES = ("taptr", "torch", "torchvision", "numpy", "opencv-python-headless", "pillow")


def package_versions() -> dict[str, str | None]:
    """Python's and the relevant packages' versions (None where not installed)."""
    versions: dict[str, str | None] = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def git_commit() -> str | None:
    """The commit of the git checkout taptr runs from, or None (installed, or no git)."""
    package = Path(__file__).resolve().parents[1]
    try:
        # only a checkout that tracks taptr's own files counts (not a repo that merely
        # contains a virtual environment with taptr installed)
        subprocess.run(
            ["git", "ls-files", "--error-unmatch", "__init__.py"],
            cwd=package,
            check=True,
            capture_output=True,
            timeout=10,
        )
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=package,
            check=True,
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def build_report(
    config: Mapping[str, Any], results: list[VideoResult], versions: Mapping[str, Any]
) -> dict[str, Any]:
    """The ``results.json`` content.

    Args:
        config: the resolved configuration; must hold dataset, mode, protocol and tracker.
        results: every video's result, in dataset order.
        versions: `package_versions` output.
    """
    videos = []
    for result in results:
        entry: dict[str, Any] = {
            "name": result.name,
            "num_points": result.num_points,
            "num_frames": result.num_frames,
        }
        entry.update({k: _finite_or_none(result.metrics[k]) for k in METRIC_NAMES})
        entry["seconds"] = round(result.seconds, 4)
        videos.append(entry)
    mean = mean_over_videos([r.metrics for r in results])
    return {
        "dataset": config["dataset"],
        "mode": config["mode"],
        "protocol": config["protocol"],
        "tracker": config["tracker"],
        "config": dict(config),
        "versions": dict(versions),
        "git_commit": git_commit(),
        "videos": videos,
        "mean": {k: _finite_or_none(v) for k, v in mean.items()},
    }


def write_report(report: Mapping[str, Any], out_dir: str | os.PathLike[str]) -> list[Path]:
    """Writes ``results.json`` and ``videos.csv`` (with a final mean row), atomically."""
    out = Path(out_dir)
    json_path, csv_path = out / RESULTS_FILE, out / TABLE_FILE
    with atomic_path(json_path) as tmp:
        tmp.write_text(json.dumps(report, indent=2, allow_nan=False) + "\n")
    columns = ["name", "num_frames", "num_points", *METRIC_NAMES, "seconds"]
    with atomic_path(csv_path) as tmp, tmp.open("w", newline="") as stream:
        writer = csv.DictWriter(stream, columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(report["videos"])
        writer.writerow({"name": "mean", **report["mean"]})
    return [json_path, csv_path]


def format_table(report: Mapping[str, Any]) -> str:
    """Per-video rows and the mean, metrics in percent as papers print them."""

    def percent(value: float | None) -> str:
        return "-" if value is None else f"{100 * value:.1f}"

    videos = report["videos"]
    width = max([len("video"), len("mean"), *(len(v["name"]) for v in videos)])
    header = f"{'video':<{width}}  frames  points     AJ  <δavg     OA  seconds"
    lines = [header, "-" * len(header)]
    for video in videos:
        lines.append(
            f"{video['name']:<{width}}  {video['num_frames']:>6}  {video['num_points']:>6}"
            f"  {percent(video['average_jaccard']):>5}  "
            f"{percent(video['average_pts_within_thresh']):>5}  "
            f"{percent(video['occlusion_accuracy']):>5}  {video['seconds']:>7.2f}"
        )
    mean = report["mean"]
    seconds = sum(v["seconds"] for v in videos) / max(len(videos), 1)
    lines += [
        "-" * len(header),
        f"{'mean':<{width}}  {'':>6}  {'':>6}  {percent(mean['average_jaccard']):>5}  "
        f"{percent(mean['average_pts_within_thresh']):>5}  "
        f"{percent(mean['occlusion_accuracy']):>5}  {seconds:>7.2f}",
    ]
    return "\n".join(lines)
