"""``taptr-export.json``: the manifest of an export folder, read bounded and written whole.

Every export (TAPTR v1 and v2's window graphs, TAPTRv3's step) writes one manifest beside
its graphs. Reading it takes the standard library only, no torch and no numpy: the file
must be a regular file of at most `MAX_MANIFEST_BYTES`, UTF-8 JSON nested no deeper than
a manifest needs, whose ``taptr_export`` format is the one this taptr reads. What its
keys hold is checked by the model's own schema (`taptr.onnx.v3_manifest`,
`taptr.export.manifest`). Every error is one line naming the file.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from taptr.io.atomic import atomic_path
from taptr.io.nesting import check_nesting
from taptr.onnx.export_files import MAX_MANIFEST_BYTES, read_bounded
from taptr.onnx.manifest_schema import ManifestError

MANIFEST_NAME = "taptr-export.json"
FORMAT_VERSION = 1
"""The manifest format this taptr reads and writes (``taptr_export``)."""

MAX_NESTING = 8
"""Deepest nesting of a manifest: graphs → graph → inputs → tensor → shape is 5."""


def manifest_path(directory: str | os.PathLike[str]) -> Path:
    """Where an export folder's manifest is."""
    return Path(directory) / MANIFEST_NAME


def read_manifest(directory: str | os.PathLike[str]) -> dict[str, Any]:
    """The manifest of an export folder (any model) as a dict, its format version checked.

    Raises:
        FileNotFoundError: no manifest there (not an export folder).
        ManifestError: not a regular file, too large, not UTF-8 JSON, nested too deeply,
            not an object, or of another format version.
    """
    path = manifest_path(directory)
    if not os.path.lexists(path):
        raise FileNotFoundError(f"{directory} is not a taptr export folder (no {MANIFEST_NAME})")
    try:
        raw = read_bounded(path, MAX_MANIFEST_BYTES, "the export manifest")
    except (ValueError, FileNotFoundError) as error:
        raise ManifestError(str(error)) from None
    data = _decoded(raw, path)
    version = data.pop("taptr_export", None)
    if version != FORMAT_VERSION or isinstance(version, bool):
        shown = json.dumps(version)[:20]
        raise ManifestError(
            f"{path}: 'taptr_export' is {shown}: this taptr reads format {FORMAT_VERSION}"
        )
    return data


def _decoded(raw: bytes, path: Path) -> dict[str, Any]:
    """The JSON object in ``raw``; one-line errors naming ``path``."""
    try:
        data = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as error:
        raise ManifestError(f"{path}: not UTF-8 text (byte {error.start})") from None
    except json.JSONDecodeError as error:
        raise ManifestError(f"{path}: not JSON ({error.msg}, line {error.lineno})") from None
    except RecursionError:
        raise ManifestError(f"{path}: JSON nested too deeply") from None
    try:
        check_nesting(data, str(path), MAX_NESTING)
    except ValueError as error:
        raise ManifestError(str(error)) from None
    if not isinstance(data, dict):
        raise ManifestError(f"{path}: must hold a JSON object, got {type(data).__name__}")
    return data


def write_manifest(
    directory: str | os.PathLike[str], fields: dict[str, Any], indent: int = 2
) -> Path:
    """Writes the manifest of an export folder, whole or not at all, never through a link.

    Args:
        directory: the export folder.
        fields: the manifest's fields; the format version is added first.
        indent: JSON indentation.
    """
    path = manifest_path(directory)
    data = {"taptr_export": FORMAT_VERSION, **fields}
    with atomic_path(path) as temporary:
        temporary.write_text(json.dumps(data, indent=indent) + "\n")
    return path
