"""Speed-only choices measured once per machine and shape, and remembered on disk.

Some settings change how fast the model runs and nothing else (which deformable-attention
kernel, how many frames per encoder call), and which is faster depends on the chip, the
thread count and the frame size: on a GPU one frame per encoder call is launch-bound, on a
CPU large frames want one at a time to stay in cache and small ones want a few
(docs/BENCHMARKS.md). Such a choice is timed on the machine the first time a shape asks
for it and written, under a key naming the machine, the model and the shape, to a small
JSON file: ``$TAPTR_MEASURED`` if set, else ``$XDG_CACHE_HOME/taptr/measured.json`` (or
``~/.cache/taptr/measured.json``). A second run reads it and measures nothing.

A file that cannot be read or written costs only the measurement: the choice is then
measured again and tracking goes on. The file is read only when it is a regular file of at
most `MAX_BYTES`, each value is checked by the choice that asks for it (a wrong one is
measured again), and it is replaced only when it is taptr's own (it names itself in
`FORMAT`) or missing or empty: any other file at that path is left alone, with a warning
naming it and ``TAPTR_MEASURED`` (`taptr.runtime.measured_file`).
"""

from __future__ import annotations

import hashlib
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from taptr.model.ops.cpu_features import cpu_capability
from taptr.runtime.measured_file import read_choices, write_choices

TOLERANCE = 0.03
"""A measured alternative must be this much faster than the setting it would replace (the
execution's own, or a smaller frames-per-call that holds less memory): timings on a busy
machine move by a few percent."""


def cpu_name(cpuinfo: str | os.PathLike[str] = "/proc/cpuinfo") -> str:
    """The CPU's model name where Linux reports it, else the architecture.

    Part of every key, because the same PyTorch build runs its float32 products at very
    different rates on Intel and AMD CPUs (`taptr.model.ops.dense`).
    """
    try:
        for line in Path(cpuinfo).read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and value.strip():
                return value.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def synchronize(device: torch.device) -> None:
    """Waits for the work queued on an accelerator (nothing to wait for on a CPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    elif device.type == "mps":
        torch.mps.synchronize()


def best_seconds(
    run: Callable[[], object],
    device: torch.device,
    repeats: int = 3,
    clock: Callable[[], float] = time.perf_counter,
) -> float:
    """Seconds of the fastest of ``repeats`` calls of ``run``, after one untimed call.

    The untimed call pays for what a first call does once (kernel selection, allocation,
    weight copies); the device is synchronised around each timed call.
    """
    run()
    best = float("inf")
    for _ in range(repeats):
        synchronize(device)
        start = clock()
        run()
        synchronize(device)
        best = min(best, clock() - start)
    return best


def measured_path() -> Path:
    """The file the measured choices are kept in."""
    explicit = os.environ.get("TAPTR_MEASURED")
    if explicit:
        return Path(explicit)
    cache = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(cache) / "taptr" / "measured.json"


def device_name(device: torch.device) -> str:
    """What runs the model: the accelerator's name, or the CPU's name and thread count."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    if device.type == "cpu":
        capability = cpu_capability()  # a CPU simulated by TAPTR_CPU keeps its own choices
        return f"{cpu_name()} ({capability}, {torch.get_num_threads()} threads)"
    return device.type


def choice_key(what: str, device: torch.device, model_signature: str, shape: str) -> str:
    """The key a choice is kept under: the choice, machine, torch, model and shape."""
    model = hashlib.sha1(model_signature.encode()).hexdigest()[:12]
    return f"{what} | {device_name(device)} | torch {torch.__version__} | {model} | {shape}"


def kept_choice(key: str, path: Path | None = None) -> Any:
    """The value kept under ``key`` (None when there is none); ``path``: default `measured_path`."""
    return read_choices(path or measured_path()).choices.get(key)


def keep(key: str, value: Any, path: Path | None = None) -> None:
    """Keeps ``value`` under ``key``, replacing what was there (JSON values only).

    Read just before writing, so that what another process wrote meanwhile stays; a file
    that is not taptr's own is left alone (`taptr.runtime.measured_file`).
    """
    path = path or measured_path()
    kept = read_choices(path)
    if kept.ours:
        write_choices(path, {**kept.choices, key: value})


def remembered(
    key: str,
    measure: Callable[[], Any],
    path: Path | None = None,
    valid: Callable[[Any], bool] | None = None,
) -> Any:
    """The choice kept under ``key``, measured (and kept) the first time it is asked for.

    Args:
        key: `choice_key` of the choice.
        measure: times the candidates and returns the winner (a JSON value).
        path: the file; default `measured_path`.
        valid: whether a value read from the file is one ``measure`` could return; a value
            that is not (edited, or written by another version) is measured again.
    """
    path = path or measured_path()
    kept = read_choices(path)
    if key in kept.choices and (valid is None or valid(kept.choices[key])):
        return kept.choices[key]
    value = measure()
    keep(key, value, path)
    return value
