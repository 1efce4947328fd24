"""How many threads a CPU run takes, and how its idle threads wait.

Every engine splits each product and convolution over its threads and waits at the end
for the slowest. On a machine that other work shares, one of those threads is often
descheduled: the others then wait at every barrier, spinning on a core the other work
wanted (OpenMP's and onnxruntime's pools spin before they sleep), and a frame costs
several times what one thread alone would take. So the count follows the cores that are
free when the run starts, and idle threads sleep instead of spinning
(``OMP_WAIT_POLICY=PASSIVE``, onnxruntime's ``allow_spinning`` off), which costs little
where nothing else runs. ``--threads`` (``OMP_NUM_THREADS`` likewise) overrides the
count; docs/BENCHMARKS.md has the measurements behind the rule.

Torch-free: the wait policy must be set before the OpenMP runtime loads with torch.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

WAIT_VARIABLE = "OMP_WAIT_POLICY"
"""Read once, when libgomp loads with torch."""

SAMPLE_SECONDS = 0.1
"""How long the free cores are watched before a run (`/proc/stat`)."""

BUSY_SHARE = 0.5
"""A core counts as taken when other work kept it busy at least this share of the sample."""


@dataclass(frozen=True)
class ThreadChoice:
    """The threads a run takes, and why.

    Attributes:
        threads: threads for products and convolutions.
        cores: cores this process may run on (affinity and the cgroup's CPU quota).
        busy: cores that other work kept busy while sampled (None: not measured).
        source: ``--threads``, ``OMP_NUM_THREADS`` or ``free cores``.
    """

    threads: int
    cores: int
    busy: float | None
    source: str

    def describe(self) -> str:
        """One line for ``-v``: the count and where it comes from."""
        load = "" if self.busy is None else f", {self.busy:.1f} busy with other work"
        return f"{self.threads} thread(s) of {self.cores} core(s) ({self.source}{load})"


def sleep_when_idle() -> None:
    """Makes OpenMP's idle threads sleep rather than spin, unless the user chose a policy.

    Takes effect only before torch is first imported (libgomp reads it once).
    """
    if not os.environ.get(WAIT_VARIABLE, "").strip():
        os.environ[WAIT_VARIABLE] = "PASSIVE"


def idle_threads_spin() -> bool:
    """Whether the wait policy in force lets idle threads spin (the other engines follow it)."""
    return os.environ.get(WAIT_VARIABLE, "").strip().upper() == "ACTIVE"


def usable_cores() -> int:
    """Cores this process may use: its affinity, capped by a cgroup CPU quota."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    quota = cgroup_quota()
    return max(1, min(cores, math.ceil(quota)) if quota else cores)


def cgroup_quota(root: Path = Path("/sys/fs/cgroup")) -> float | None:
    """The cgroup's CPU quota in cores (``cpu.max``, cgroup v2), None without one."""
    try:
        fields = (root / "cpu.max").read_text().split()
        return int(fields[0]) / int(fields[1]) if fields[0] != "max" else None
    except (OSError, ValueError, IndexError, ZeroDivisionError):
        return None


def busy_cores(seconds: float = SAMPLE_SECONDS, stat: Path = Path("/proc/stat")) -> float | None:
    """Cores kept busy by other work over ``seconds`` (this process sleeps meanwhile).

    Returns None where ``/proc/stat`` cannot be read (not Linux).
    """
    first = _cpu_times(stat)
    if first is None:
        return None
    time.sleep(seconds)
    second = _cpu_times(stat)
    if second is None:
        return None
    (busy_a, total_a), (busy_b, total_b) = first, second
    if total_b <= total_a:
        return 0.0
    cores = os.cpu_count() or 1
    return cores * (busy_b - busy_a) / (total_b - total_a)


def _cpu_times(stat: Path) -> tuple[int, int] | None:
    """(busy, total) jiffies over all cores, from the ``cpu`` line of ``/proc/stat``."""
    try:
        fields = [int(v) for v in stat.read_text().splitlines()[0].split()[1:]]
    except (OSError, ValueError, IndexError):
        return None
    idle = sum(fields[3:5])  # idle and iowait
    return sum(fields[:8]) - idle, sum(fields[:8])  # guest time is counted in user already


def choose_threads(requested: int | None = None) -> ThreadChoice:
    """The thread count for a CPU run: ``requested``, else ``OMP_NUM_THREADS``, else free cores.

    Args:
        requested: ``--threads`` (None: choose).

    Raises:
        ValueError: ``requested`` below 1.
    """
    cores = usable_cores()
    if requested is not None:
        if requested < 1:
            raise ValueError(f"--threads {requested}: must be at least 1")
        return ThreadChoice(requested, cores, None, "--threads")
    from_env = os.environ.get("OMP_NUM_THREADS", "").strip()
    if from_env.isdigit() and int(from_env) >= 1:
        return ThreadChoice(int(from_env), cores, None, "OMP_NUM_THREADS")
    busy = busy_cores()
    if busy is None:
        return ThreadChoice(cores, cores, None, "free cores")
    taken = math.floor(busy + (1 - BUSY_SHARE))
    return ThreadChoice(max(1, cores - taken), cores, busy, "free cores")


def use_threads(requested: int | None = None) -> ThreadChoice:
    """Chooses the thread count (`choose_threads`) and hands it to torch; logs it at ``-v``."""
    import logging

    import torch

    choice = choose_threads(requested)
    torch.set_num_threads(choice.threads)
    logging.getLogger(__name__).info("CPU: %s", choice.describe())
    return choice
