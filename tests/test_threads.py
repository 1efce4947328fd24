"""The thread count of a CPU run and the wait policy of its idle threads (taptr.runtime.threads)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from taptr.runtime import threads


@pytest.fixture
def two_cores(monkeypatch):
    monkeypatch.setattr(threads, "usable_cores", lambda: 2)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)


@pytest.mark.parametrize(("busy", "expected"), [(0.0, 2), (0.3, 2), (0.6, 1), (1.6, 1), (2.0, 1)])
def test_free_cores_decide(two_cores, monkeypatch, busy, expected):
    monkeypatch.setattr(threads, "busy_cores", lambda: busy)
    choice = threads.choose_threads()
    assert (choice.threads, choice.source, choice.busy) == (expected, "free cores", busy)
    assert f"{expected} thread(s) of 2 core(s)" in choice.describe()


def test_requested_and_environment_win(two_cores, monkeypatch):
    monkeypatch.setattr(threads, "busy_cores", lambda: pytest.fail("sampled"))
    assert threads.choose_threads(3).threads == 3
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert (threads.choose_threads().threads, threads.choose_threads().source) == (
        1,
        "OMP_NUM_THREADS",
    )
    with pytest.raises(ValueError, match="--threads 0"):
        threads.choose_threads(0)


def test_unknown_load_takes_every_core(two_cores, monkeypatch):
    monkeypatch.setattr(threads, "busy_cores", lambda: None)
    assert threads.choose_threads().threads == 2


def test_cgroup_quota(tmp_path):
    (tmp_path / "cpu.max").write_text("150000 100000\n")
    assert threads.cgroup_quota(tmp_path) == 1.5
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert threads.cgroup_quota(tmp_path) is None
    (tmp_path / "cpu.max").write_text("garbage\n")
    assert threads.cgroup_quota(tmp_path) is None
    assert threads.cgroup_quota(tmp_path / "missing") is None


def test_busy_cores_reads_proc_stat(tmp_path):
    stat = tmp_path / "stat"
    stat.write_text("cpu  100 0 100 800 0 0 0 0 0 0\ncpu0 1 2 3\n")
    assert threads._cpu_times(stat) == (200, 1000)
    assert threads.busy_cores(0.0, stat) == 0.0  # nothing moved between the reads
    assert threads.busy_cores(0.0, tmp_path / "missing") is None
    if os.path.exists("/proc/stat"):
        busy = threads.busy_cores(0.05)
        assert busy is not None and 0.0 <= busy <= (os.cpu_count() or 1) + 1e-6


def test_the_command_makes_idle_threads_sleep_before_torch_loads(tmp_path):
    code = (
        "import os, sys\n"
        "from taptr.cli import main\n"
        "sys.argv = ['taptr', 'sample-video', '--help']\n"
        "try:\n    main.main()\nexcept SystemExit:\n    pass\n"
        "print(os.environ.get('OMP_WAIT_POLICY'), 'torch' in sys.modules)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.stdout.split()[-2:] == ["PASSIVE", "False"]
    env["OMP_WAIT_POLICY"] = "ACTIVE"  # the user's choice stands
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.stdout.split()[-2:] == ["ACTIVE", "False"]
