"""TAPTRv3's graphs exported once per checkpoint and kept: what ``--engine`` runs.

The first run of a checkpoint in a graph engine (``taptr track --engine onnxruntime``)
exports it (`taptr.export.v3_graphs.export_v3`, a minute for the paper's R18 model on two
cores) into the cache, ``$TAPTR_EXPORT_DIR`` or ``~/.cache/taptr/exports``, and says so in
one line; later runs find the folder and open it. Each entry's name is the SHA-256 of what
makes its graphs: the checkpoint file's bytes, the input size, the export's format and
taptr's version (`export_key`). History limits, support points and thresholds are the
loop's, not the graphs', so they share an entry.

An entry is exported into a hidden temporary folder beside it and renamed into place
whole, so a killed export leaves no half entry and two processes exporting the same one at
once keep the first that finishes. An entry that fails its checks (its key file or
manifest damaged, a graph missing) is removed and exported again, with one line.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from taptr.io.atomic import remove_stale_temporaries

CACHE_VARIABLE = "TAPTR_EXPORT_DIR"
"""Environment variable naming the cache folder."""

KEY_FILE = "taptr-cache.json"
"""The entry's key, written last into the temporary folder: an entry without it is damaged."""

FORMAT = 1
"""Version of the cache's layout; entries of another version are other entries."""

PREFIX, SUFFIX = ".export.", ".tmp"
"""Name parts of the temporary folders an export writes into (`remove_stale_temporaries`)."""


@dataclass(frozen=True)
class ExportRequest:
    """What an entry is exported from.

    Attributes:
        checkpoint: the checkpoint file.
        name: what the user called it (for messages).
        input_size: (H, W) the graphs take.
    """

    checkpoint: Path
    name: str
    input_size: tuple[int, int]


def cache_root() -> Path:
    """``$TAPTR_EXPORT_DIR``, else ``~/.cache/taptr/exports``."""
    chosen = os.environ.get(CACHE_VARIABLE)
    return Path(chosen) if chosen else Path.home() / ".cache" / "taptr" / "exports"


def export_key(request: ExportRequest) -> dict[str, object]:
    """What the entry's graphs depend on (JSON-ready); its SHA-256 names the entry."""
    from taptr import __version__
    from taptr.weights.registry import file_sha256

    return {
        "format": FORMAT,
        "taptr": __version__,
        "checkpoint_sha256": file_sha256(request.checkpoint),
        "input_size": list(request.input_size),
    }


def entry_folder(key: dict[str, object]) -> Path:
    """The cache folder of ``key``."""
    text = json.dumps(key, sort_keys=True)
    return cache_root() / hashlib.sha256(text.encode()).hexdigest()


def cached_export(request: ExportRequest, engine: str) -> Path:
    """The entry of ``request``, exported first when missing or damaged (one line each).

    Args:
        request: the checkpoint and input size.
        engine: the engine that asks (for the line).

    Raises:
        ModuleNotFoundError: onnx or onnxscript is missing (an export is needed).
    """
    key = export_key(request)
    folder = entry_folder(key)
    problem = entry_problem(folder, key)
    if problem is None:
        return folder
    if folder.exists():
        say(f"taptr: the exported graphs in {folder} are damaged ({problem}); exporting again")
        discard(folder)
    return export_entry(request, key, folder, engine)


def entry_problem(folder: Path, key: dict[str, object]) -> str | None:
    """Why ``folder`` is not a finished entry of ``key`` (None: it is)."""
    from taptr.onnx.graph_engines import graph_files
    from taptr.onnx.v3_manifest import V3Manifest

    if not folder.exists():
        return "missing"
    try:
        recorded = json.loads((folder / KEY_FILE).read_text(encoding="utf-8"))
        if recorded != key:
            return f"{KEY_FILE} records another export"
        graph_files(V3Manifest.load(folder), folder)
    except (OSError, ValueError) as error:  # ManifestError and JSON errors included
        return " ".join(str(error).split())[:200]
    return None


def export_entry(request: ExportRequest, key: dict[str, object], folder: Path, engine: str) -> Path:
    """Exports ``request`` into a temporary folder and renames it to ``folder``."""
    from taptr.export.v3_graphs import export_v3
    from taptr.weights.registry import resolve_model

    root = cache_root()
    root.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(root, PREFIX, SUFFIX)
    began = time.perf_counter()
    staging = Path(tempfile.mkdtemp(prefix=f"{PREFIX}{os.getpid()}-", suffix=SUFFIX, dir=root))
    try:
        model = resolve_model(str(request.checkpoint))  # TAPTRv3: the caller checked its config
        export_v3(model, staging, request.input_size)  # type: ignore[arg-type]
        (staging / KEY_FILE).write_text(json.dumps(key, sort_keys=True) + "\n", encoding="utf-8")
        os.chmod(staging, 0o755)  # mkdtemp's 0700 would hide the entry from other users
        try:
            staging.rename(folder)
        except OSError:  # another process finished the same entry first: keep its
            if entry_problem(folder, key) is not None:
                raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    seconds = time.perf_counter() - began
    say(
        f"taptr: exported {request.name} for {engine} once to {folder} ({seconds:.1f} s); "
        "later runs reuse it"
    )
    return folder


def discard(folder: Path) -> None:
    """Removes a damaged entry (a link is unlinked, never followed)."""
    if folder.is_symlink() or not folder.is_dir():
        folder.unlink(missing_ok=True)
    else:
        shutil.rmtree(folder, ignore_errors=True)


def say(line: str) -> None:
    """One line on stderr, where the commands' notes go (stdout carries results)."""
    sys.stderr.write(line + "\n")
    sys.stderr.flush()
