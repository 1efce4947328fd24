"""TAPTRv3's weights on Google Drive: where they are, where they go, how a file is checked.

`MANUAL` names the authors' two TAPTRv3 checkpoints. `manual_path` reads one from the
weights folder (`weights_dir`, ``TAPTR_WEIGHTS_DIR``) and, when it is missing, downloads it
there once through `taptr.drive` after a one-line notice of its licence; without gdown,
offline or when Drive refuses, one message gives the link, the licence and where to put
the file. `check_download` is the check of any named file taptr fetched (from Drive or the
Hugging Face Hub): not a web page, not smaller than the weights it should hold, and the
architecture its name promises (`taptr.checkpoint_identity`).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

from taptr.checkpoint import CheckpointError, check_architecture, is_web_page, read_checkpoint
from taptr.checkpoint_identity import weights_bytes
from taptr.config import get_config

logger = logging.getLogger(__name__)

IDEA_LICENCE = "IDEA License 1.0, non-commercial use only"
"""The licence of the authors' released weights (TAPTR v1, v2 and v3)."""


@dataclass(frozen=True)
class ManualWeights:
    """Weights the authors host on Google Drive.

    Drive answers scripted downloads of large files (``curl``, ``wget``) with a
    confirmation web page; ``gdown`` reads it (`taptr.drive`). taptr reads the file from
    `weights_dir`, downloads it there once when it is missing and gdown is installed, and
    otherwise says where to get it and where to put it.

    Attributes:
        url: the authors' link to the file.
        filename: the file's name, as the authors' evaluation script expects it.
        preset: the architecture the file holds (a key of `taptr.config.PRESETS`).
        title: the model's name in messages.
        licence: the weights' licence.
    """

    url: str
    filename: str
    preset: str
    title: str
    licence: str


MANUAL = {
    "taptrv3-official": ManualWeights(
        "https://drive.google.com/file/d/1frPX9R_nKDG8FmL-vH6l_2HsJfhvEjtg",
        "TAPTRv3_resnet18_384x512.pth",
        "taptrv3",
        "TAPTRv3 (ResNet-18, 384 × 512)",
        IDEA_LICENCE,
    ),
    "taptrv3-r50-official": ManualWeights(
        "https://drive.google.com/file/d/19iql2VTqGIeoyg_wt3JjpohszN5UE6s1",
        "TAPTRv3_resnet50_512x512.pth",
        "taptrv3-r50",
        "TAPTRv3 (ResNet-50, 512 × 512)",
        IDEA_LICENCE,
    ),
}
"""Weights on Google Drive: name → where the authors host the file and what it holds."""


def weights_dir() -> Path:
    """Where hand-downloaded weights are looked for.

    ``TAPTR_WEIGHTS_DIR`` (read now, not at import), else ``~/.cache/taptr/weights``.
    """
    folder = os.environ.get("TAPTR_WEIGHTS_DIR")
    return Path(folder) if folder else Path.home() / ".cache" / "taptr" / "weights"


def manual_path(name: str) -> Path:
    """The file of Drive weights ``name`` in `weights_dir`, downloaded once when missing.

    The download (`taptr.drive.fetch`) says the licence first, shows a progress bar, and
    keeps the file only when `check_download` accepts it.

    Raises:
        FileNotFoundError: it is not there and cannot be downloaded (no gdown, offline,
            Drive unreachable, a broken transfer); the message says why, and gives the
            link, the licence and where to put the file (or the path to pass instead).
        CheckpointError: the download is not the weights (`check_download`); nothing
            was kept.
    """
    entry = MANUAL[name]
    path = weights_dir() / entry.filename
    if path.is_file():
        return path
    from taptr import drive

    if drive.can_download():
        logger.warning(
            "downloading %s weights (%s) from %s into %s: %s",
            entry.title,
            entry.filename,
            entry.url,
            path.parent,
            entry.licence,
        )
    try:
        return drive.fetch(entry.url, path, lambda file: check_download(file, name, entry.preset))
    except drive.DriveError as error:
        raise FileNotFoundError(_manual_message(name, entry, path, str(error))) from None


def _manual_message(name: str, entry: ManualWeights, path: Path, reason: str) -> str:
    """Where to get Drive weights by hand, when taptr could not download them."""
    return (
        f"{name}: {entry.filename} is not in {path.parent} and {reason}. The authors host "
        f"{entry.title} on Google Drive ({entry.licence}): open {entry.url} in a browser and "
        f"download it (curl and wget get Drive's confirmation page, not the file), then put it "
        f"at {path} (or set TAPTR_WEIGHTS_DIR to its folder), or pass its path: --checkpoint "
        f"/path/to/{entry.filename} on the command line, "
        f'taptr.from_pretrained("/path/to/{entry.filename}") in Python'
    )


def check_download(path: Path, name: str, preset: str) -> None:
    """Raises `CheckpointError` unless ``path`` holds the weights ``name`` promises.

    Refused, each with what the file is: a web page (Drive's confirmation or error page
    saved instead of the file), a file smaller than the weights of ``preset`` in float16
    (a truncated transfer), a file that is no checkpoint, and another model's weights.
    """
    if is_web_page(path):
        raise CheckpointError(
            f"the download of {name} is a web page (HTML), not weights: Drive answered with a "
            "page instead of the file (a quota or permission message); try again later, or "
            "download it in a browser"
        )
    size, least = path.stat().st_size, weights_bytes(get_config(preset), bytes_per_value=2)
    if size < least:
        raise CheckpointError(
            f"the download of {name} is {size:,} bytes, but its weights take at least "
            f"{least:,}: the transfer was cut short; try again"
        )
    config, _ = read_checkpoint(path)
    check_architecture(config, f"the download of {name}", name, preset)
