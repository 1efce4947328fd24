"""The built wheel installs and works outside the source tree (slow: builds and installs)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "check_wheel.py"
WEIGHTS = Path("src") / "taptr" / "weights" / "taptr-small-synthetic.pth"

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(shutil.which("git") is None, reason="needs git to list the sources"),
]


def _check(repo: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": ""}
    return subprocess.run(
        [sys.executable, str(repo / "scripts" / "check_wheel.py")],
        cwd=repo,
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )


def test_wheel_installs_and_runs_outside_the_tree():
    done = _check(REPO)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "wheel check passed" in done.stdout


def test_bundled_weights_reach_the_installed_package(tmp_path):
    """A copy of the sources with a stand-in weights file: the wheel must carry it."""
    listing = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=REPO,
        capture_output=True,
        check=True,
    ).stdout.decode()
    copy = tmp_path / "repo"
    for name in filter(None, listing.split("\0")):
        if (REPO / name).is_file() and name != str(WEIGHTS):
            (copy / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, copy / name)
    subprocess.run(["git", "init", "-q"], cwd=copy, check=True)
    import taptr

    torch.manual_seed(0)
    taptr.save_checkpoint(taptr.build_model("tiny"), copy / WEIGHTS)
    done = _check(copy)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "bundled model input size (64, 64)" in done.stdout
