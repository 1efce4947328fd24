"""Atomic writes: a failure never leaves a half-written file or a half-replaced folder.

A temporary file is a hidden sibling of its target, ``.{stem}.{pid}-{random}.tmp{suffix}``;
the staging folder of a result folder is a hidden ``.taptr.{pid}-{random}.tmp`` inside it.
An exception (Ctrl-C included, and SIGTERM under the ``taptr`` command, which turns it into
one) removes them; a process killed outright (SIGKILL, power loss) cannot, so every later
write to the same place first removes the temporaries whose process is gone.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import tempfile
import threading
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

LEGACY_STALE_SECONDS = 3600
"""Temporaries named without a process id (by older taptr) are stale after this long."""

STAGING_PREFIX = ".taptr."
"""Name prefix of the hidden staging folders of `result_folder`."""

_OWNER = re.compile(r"(?P<pid>\d+)-[^.]+|[a-z0-9_]{8}")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yields a temporary path next to ``path`` and renames it onto ``path`` on success.

    The temporary file keeps the target's suffix (some writers choose the format from
    it). On an exception the temporary file is removed and ``path`` is left untouched.
    Stale temporaries of the same target from killed processes are removed first.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    prefix, suffix = f".{target.stem}.", f".tmp{target.suffix}"
    remove_stale_temporaries(target.parent, prefix, suffix)
    fd, tmp_name = tempfile.mkstemp(
        prefix=f"{prefix}{os.getpid()}-", suffix=suffix, dir=target.parent
    )
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        # mkstemp creates 0600 files; give the result the permissions a plain open() would
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def result_folder(folder: str | os.PathLike[str], owned: Iterable[str]) -> Iterator[Path]:
    """Yields an empty staging folder whose files replace a command's results in ``folder``.

    The files are written into a hidden staging folder inside ``folder`` (``.taptr.{pid}-
    {random}.tmp``, so only ``folder`` itself must be writable, and ``--out .`` works); on
    success they are renamed into ``folder`` together, with SIGINT and SIGTERM held back
    meanwhile, and the files named in ``owned`` that this run did not write (an earlier
    run's optional outputs) are removed, so the folder holds either the earlier results
    or the new ones, never a mix. Other files in ``folder`` are left alone. On an exception
    the staging folder is removed, ``folder`` keeps its files, and a ``folder`` this call
    created is removed again.

    Args:
        folder: the result folder; created if missing.
        owned: names of every file the command may write there.

    Raises:
        NotADirectoryError: ``folder`` is an existing file.
        ValueError: one of the ``owned`` names in ``folder`` is not a file
            (`check_result_names`), checked before the block runs and again before the
            files are renamed; a rename that fails all the same puts the earlier files back.
    """
    target = Path(folder)
    if target.exists() and not target.is_dir():
        raise NotADirectoryError(f"{target} is a file, not a folder")
    owned = tuple(owned)
    check_result_names(target, owned)
    created = not target.exists()
    target.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(target, STAGING_PREFIX, ".tmp")
    staging = Path(
        tempfile.mkdtemp(prefix=f"{STAGING_PREFIX}{os.getpid()}-", suffix=".tmp", dir=target)
    )
    done = False
    try:
        yield staging
        with deferred_signals():
            check_result_names(target, owned)
            _swap_in(staging, target, owned)
        done = True
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        if created and not done:
            with contextlib.suppress(OSError):  # not empty: someone else wrote there meanwhile
                target.rmdir()


def check_result_names(folder: Path, owned: Iterable[str]) -> None:
    """Raises a ValueError when a name a command writes in ``folder`` is not a file there.

    A folder (or FIFO, device, socket) named ``settings.json`` inside a result folder could
    not be replaced by the new file, so the run would fail after tracking; said up front.
    """
    for name in owned:
        path = folder / name
        if path.is_symlink() or not path.exists() or path.is_file():
            continue
        described = "a folder" if path.is_dir() else "not a regular file"
        raise ValueError(
            f"{path} is {described}, where taptr writes its result file {name}: remove it, "
            "or choose another output folder"
        )


def _swap_in(staging: Path, target: Path, owned: Iterable[str]) -> None:
    """Moves the staged files into ``target``, replacing the ``owned`` ones, all or none.

    The earlier files are first moved into a hidden folder of ``staging``; if a rename
    fails, the new files are removed and the earlier ones put back before the error rises.
    """
    written = sorted(entry.name for entry in staging.iterdir())
    previous = staging / ".previous"
    previous.mkdir()
    moved: list[str] = []
    placed: list[str] = []
    try:
        for name in owned:
            if (target / name).is_symlink() or (target / name).is_file():
                os.replace(target / name, previous / name)
                moved.append(name)
        for name in written:
            os.replace(staging / name, target / name)
            placed.append(name)
    except OSError:
        for name in placed:
            (target / name).unlink(missing_ok=True)
        for name in moved:
            os.replace(previous / name, target / name)
        raise


def remove_stale_temporaries(folder: Path, prefix: str, suffix: str) -> list[Path]:
    """Removes ``{prefix}{owner}{suffix}`` entries of ``folder`` left by processes now gone.

    The owner part is ``{pid}-{random}``; an entry whose process still runs (another write
    of the same target under way) is kept. Legacy entries without a pid are removed once
    they have not changed for `LEGACY_STALE_SECONDS`.

    Returns:
        The entries removed.
    """
    removed = []
    with contextlib.suppress(OSError):
        for entry in folder.iterdir():
            name = entry.name
            if not (name.startswith(prefix) and name.endswith(suffix)):
                continue
            owner = _OWNER.fullmatch(name[len(prefix) : len(name) - len(suffix)])
            if owner is None or not _is_stale(entry, owner):
                continue
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
            removed.append(entry)
    return removed


@contextlib.contextmanager
def deferred_signals() -> Iterator[None]:
    """Holds SIGINT and SIGTERM back for the block and delivers them after it.

    Only the main thread can install signal handlers; elsewhere the block runs as is.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    numbers = (signal.SIGINT, signal.SIGTERM)
    previous = {number: signal.getsignal(number) for number in numbers}
    if any(handler is None for handler in previous.values()):  # set outside Python: keep it
        yield
        return
    for number in numbers:
        signal.signal(number, lambda signum, _frame: received.append(signum))
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
        for number in dict.fromkeys(received):
            signal.raise_signal(number)


def _is_stale(entry: Path, owner: re.Match[str]) -> bool:
    pid = owner.group("pid")
    if pid is None:
        try:
            return time.time() - entry.stat().st_mtime > LEGACY_STALE_SECONDS
        except OSError:
            return False
    return int(pid) != os.getpid() and not _process_exists(int(pid))


def _process_exists(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):  # another user's process, or not a real pid
        return True
    return True


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask
