"""Options several commands share, and the checks every command runs before its work starts.

Each check raises a one-line ValueError that names the flag as the user typed it, so that a
bad argument fails in a second instead of after a long run.
"""

from __future__ import annotations

import argparse
import glob
import os
import re
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

DEVICE_HELP = "where to run: cpu, cuda, cuda:N or mps (default: {default})"
"""Help text of every ``--device`` option."""

MIN_INPUT_SIDE = 48
"""Smallest ``--input-size`` side: below it the coarsest feature map is a single pixel."""

MAX_INPUT_SIDE = 4096
"""Largest ``--input-size`` side: 8 frames of 4096×4096 already need tens of GB."""


def add_device_argument(parser: argparse.ArgumentParser, default: str | None = None) -> None:
    """Adds ``--device`` with the help text every command shares."""
    parser.add_argument(
        "--device",
        default=default,
        help=DEVICE_HELP.format(default=default or "cuda if available, else cpu"),
    )


def add_frames_per_call_argument(parser: argparse.ArgumentParser) -> None:
    """``--frames-per-call auto|N`` (`taptr.runtime.encode_choice`)."""
    parser.add_argument(
        "--frames-per-call",
        type=_frames_per_call,
        default="auto",
        metavar="auto|N",
        help="frames per encoder call; auto times the sizes that fit this device once per "
        "machine and input size and remembers the fastest (speed only; default: auto)",
    )


def add_threads_argument(parser: argparse.ArgumentParser) -> None:
    """``--threads N`` (`taptr.runtime.threads`)."""
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        metavar="N",
        help="CPU threads for the model's products and convolutions (default: the cores "
        "that other work leaves free when the run starts, or OMP_NUM_THREADS)",
    )


def _frames_per_call(value: str) -> int | str:
    if value == "auto":
        return value
    if not value.isdigit() or int(value) < 1:
        raise argparse.ArgumentTypeError(f"expected auto or a whole number >= 1, got {value!r}")
    return int(value)


def check_device(device: str | None, flag: str = "--device") -> None:
    """Raises a ValueError unless ``device`` names a device this machine has (None: auto).

    Torch is imported only to ask about a GPU that may exist: a typo, ``cpu``, or ``cuda``
    on a machine without GPU devices costs no import.
    """
    if device is None:
        return
    if not re.fullmatch(r"(cpu|cuda|mps)(:\d+)?", device):
        raise ValueError(f"{flag} {device}: not a device; use cpu, cuda, cuda:N or mps")
    kind, _, index = device.partition(":")
    if kind == "cpu":
        return
    if kind == "cuda" and not _gpu_device_files():
        raise ValueError(f"{flag} {device}: this machine has no usable CUDA GPU; use cpu")
    import torch

    if kind == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise ValueError(f"{flag} {device}: this machine has no usable CUDA GPU; use cpu")
        if index and int(index) >= count:
            raise ValueError(f"{flag} {device}: this machine has {count} GPU(s), cuda:0..")
    elif not torch.backends.mps.is_available():
        raise ValueError(f"{flag} {device}: MPS is not available on this machine; use cpu")


def _gpu_device_files() -> bool:
    """Whether the system shows a device a CUDA (or ROCm) build of torch could use.

    False only where that is certain without torch: macOS, and Linux without NVIDIA, ROCm
    or WSL device files; elsewhere torch is asked.
    """
    if sys.platform == "darwin":
        return False
    if not sys.platform.startswith("linux"):
        return True
    devices = ("/proc/driver/nvidia", "/dev/kfd", "/dev/dxg")
    return bool(glob.glob("/dev/nvidia[0-9]*")) or any(os.path.exists(d) for d in devices)


def check_input_size(
    size: Sequence[int] | None, flag: str = "--input-size", minimum: int = MIN_INPUT_SIDE
) -> None:
    """Raises a ValueError unless both sides lie in [``minimum``, `MAX_INPUT_SIDE`]."""
    if size is None:
        return
    if not all(minimum <= side <= MAX_INPUT_SIDE for side in size):
        raise ValueError(
            f"{flag} {' '.join(map(str, size))}: each side must lie in "
            f"[{minimum}, {MAX_INPUT_SIDE}] pixels"
        )


def check_at_least(value: int | None, minimum: int, flag: str) -> None:
    """Raises a ValueError when a numeric option is below ``minimum`` (None: not given)."""
    if value is not None and value < minimum:
        raise ValueError(f"{flag} must be at least {minimum}, got {value}")


def check_output_folder(path: str | os.PathLike[str], flag: str = "--out") -> None:
    """Raises a ValueError unless ``path`` is a folder, or can be created as one."""
    target = Path(path)
    if target.is_symlink() and not target.exists():
        raise ValueError(
            f"{flag} {target} is a link to {os.readlink(target)}, which does not exist: "
            "create that folder or give another"
        )
    if target.exists() and not target.is_dir():
        raise ValueError(f"{flag} {target} is a file; give a folder")
    _check_writable(target, target, flag)


def check_output_file(
    path: str | os.PathLike[str], flag: str = "--out", suffixes: Sequence[str] = ()
) -> None:
    """Raises a ValueError unless ``path`` can be written as a file (with one of ``suffixes``)."""
    target = Path(path)
    if target.is_dir():
        example = target / f"out{suffixes[0] if suffixes else ''}"
        raise ValueError(f"{flag} {target} is a folder; give a file name, e.g. {example}")
    if suffixes and target.suffix.lower() not in suffixes:
        raise ValueError(f"{flag} {target}: the name must end in {' or '.join(suffixes)}")
    _check_writable(target.absolute().parent, target, flag)


def check_input_path(path: str | os.PathLike[str], flag: str) -> None:
    """Raises FileNotFoundError naming ``flag`` when ``path`` (a file or folder) is missing."""
    if not Path(path).exists():
        raise FileNotFoundError(f"{flag} {path}: not found")


def _check_writable(folder: Path, named: Path, flag: str) -> None:
    """``folder``, or the nearest existing folder above it, must be a folder we can write in.

    Messages name ``named``, the path as the user gave it with ``flag``.
    """
    parent = folder.absolute()
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ValueError(f"{flag} {named}: {parent} is a file, not a folder")
    # a real write: permission bits say little for root, read-only mounts or /proc
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as error:
        raise ValueError(f"{flag} {named}: cannot write in {parent} ({error.strerror})") from None
