"""TAPTRv3's weights on Google Drive: where they are, where they go, how a file is checked.

`MANUAL` names the authors' two TAPTRv3 checkpoints. `manual_path` reads one from the weights folder
(`weights_dir`, ``TAPTR_WEIGHTS_DIR``) and, when it is missing, downloads it there once through
`taptr.weights.drive_download` after a one-line notice of its licence (said once Drive answered);
without gdown, offline or when Drive refuses, one message gives the link, the licence and where to
put the file. A file already there that cannot be the weights (a web page, or a size no release of
them has: `release_bytes`) is moved aside (`set_aside`, to ``NAME.rejected``) with one line saying
so, and fetched again. `check_download` is the check of any named file taptr fetched (from Drive or
the Hugging Face Hub): not a web page, of a size a release can have, and the architecture its name
promises (`taptr.weights.identity`).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

from taptr.config import get_config
from taptr.weights.checkpoint import (
    CheckpointError,
    check_architecture,
    is_web_page,
    read_checkpoint,
)
from taptr.weights.identity import describe, same_architecture, weights_bytes

logger = logging.getLogger(__name__)

IDEA_LICENCE = "IDEA License 1.0, non-commercial use only"
"""The licence of the authors' released weights (TAPTR v1, v2 and v3)."""

RELEASE_FACTOR = 4
"""A released file holds at most this many float32 copies of its weights: the weights,
their EMA and an optimiser's two moments (the authors' files hold one: taptrv2.pth is
160 MB, its weights' size)."""

RELEASE_SLACK = 1024**2
"""Bytes a release holds besides its tensors (the pickle, the config), at most."""

WEIGHTS_VARIABLE = "TAPTR_WEIGHTS_DIR"
"""The setting that names the weights folder."""


@dataclass(frozen=True)
class ManualWeights:
    """Weights the authors host on Google Drive.

    Drive answers scripted downloads of large files (``curl``, ``wget``) with a
    confirmation web page; ``gdown`` reads it (`taptr.weights.drive_download`). taptr reads
    the file from
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

    Raises:
        NotADirectoryError: ``TAPTR_WEIGHTS_DIR`` names a file (or a path through one).
    """
    folder = os.environ.get(WEIGHTS_VARIABLE)
    if not folder:
        return Path.home() / ".cache" / "taptr" / "weights"
    path = Path(folder)
    for part in (path, *path.parents):  # the nearest part that exists must be a folder
        if part.exists():
            if not part.is_dir():
                raise NotADirectoryError(
                    f"{WEIGHTS_VARIABLE}={folder} is no folder ({part} is a file): set it "
                    "to the folder that holds the weights, or unset it for "
                    "~/.cache/taptr/weights"
                )
            break
    return path


def release_bytes(preset: str) -> tuple[int, int]:
    """(fewest, most) bytes a released file of ``preset``'s weights can have.

    Fewest: the weights in float16 (``taptr convert --half``); a smaller file is a
    transfer cut short. Most: `RELEASE_FACTOR` float32 copies and `RELEASE_SLACK`.
    """
    config = get_config(preset)
    fewest = weights_bytes(config, bytes_per_value=2)
    return fewest, RELEASE_FACTOR * weights_bytes(config) + RELEASE_SLACK


def kept_problem(path: Path, preset: str) -> str | None:
    """Why the file at ``path`` cannot be weights of ``preset``, or None.

    Read cheaply: its first bytes and its size. A file too small to hold the weights is
    read, though: a whole checkpoint of a smaller model is left to the architecture check,
    which says what it holds.
    """
    if is_web_page(path):
        return "a web page (HTML), not weights"
    size = path.stat().st_size
    fewest, most = release_bytes(preset)
    if size > most:
        return f"{size:,} bytes, more than a release of the weights holds ({most:,})"
    if size >= fewest:
        return None
    try:
        read_checkpoint(path)
    except (CheckpointError, OSError):
        return f"{size:,} bytes, but its weights take at least {fewest:,}: a transfer cut short"
    return None


def set_aside(path: Path, reason: str, name: str) -> Path:
    """Renames a bad file at ``path`` to ``NAME.rejected`` beside it and says so in one line.

    Kept rather than deleted: it may be a file of the user's, and whatever was set aside
    before is replaced.
    """
    aside = path.with_name(f"{path.name}.rejected")
    os.replace(path, aside)
    logger.warning(
        "%s is not the weights of %s (%s): moved aside to %s; fetching it again",
        path,
        name,
        reason,
        aside,
    )
    return aside


def manual_path(name: str) -> Path:
    """The file of Drive weights ``name`` in `weights_dir`, downloaded once when missing.

    A file there that cannot be the weights (`kept_problem`) is moved aside first
    (`set_aside`). The download (`taptr.weights.drive_download.fetch`) says the licence once Drive
    answered, shows a progress bar, and keeps the file only when `check_download`
    accepts it.

    Raises:
        FileNotFoundError: it is not there and cannot be downloaded (no gdown, offline,
            Drive unreachable, a broken, slow or oversized transfer); the message says
            why, and gives the link, the licence and where to put the file (or the path
            to pass instead).
        FileExistsError: a folder or another special file stands where the file goes.
        NotADirectoryError: ``TAPTR_WEIGHTS_DIR`` names a file.
        CheckpointError: the download is not the weights (`check_download`); nothing
            was kept.
    """
    entry = MANUAL[name]
    path = weights_dir() / entry.filename
    if path.is_file():
        problem = kept_problem(path, entry.preset)
        if problem is None:
            return path
        set_aside(path, problem, name)
    elif path.exists():
        raise FileExistsError(
            f"{path} is in the way of the weights of {name}: it is not a file; move it away"
        )
    from taptr.weights import drive_download

    def announce() -> None:
        logger.warning(
            "downloading %s weights (%s) from %s into %s: %s",
            entry.title,
            entry.filename,
            entry.url,
            path.parent,
            entry.licence,
        )

    try:
        return drive_download.fetch(
            entry.url,
            path,
            lambda file: check_download(file, name, entry.preset),
            largest=release_bytes(entry.preset)[1],
            announce=announce,
        )
    except drive_download.DriveError as error:
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


def check_download(path: Path, name: str, preset: str, kept: bool = False) -> None:
    """Raises `CheckpointError` unless ``path`` holds the weights ``name`` promises.

    Refused, each with what the file is: a web page (Drive's confirmation or error page
    saved instead of the file), a file of a size no release of the weights of ``preset``
    has (`release_bytes`: a truncated transfer, or something else), a file that is no
    checkpoint, and another model's weights.

    Args:
        path: the file.
        name: the weights' name.
        preset: the architecture ``name`` promises.
        kept: ``path`` is the kept file (the message says to delete it), not a download
            being checked before it is kept (the message says nothing was kept).

    Raises:
        CheckpointError: the file is not the weights; the message says what it is.
    """
    outcome = f"delete {path} and taptr fetches it again" if kept else "nothing was kept"
    problem = kept_problem(path, preset)
    if problem is not None:
        page = "HTML" in problem  # a quota or permission page: later, or by hand
        advice = "try again later, or download it in a browser" if page else "try again"
        raise CheckpointError(f"the download of {name} is {problem}; {outcome}; {advice}")
    config, _ = read_checkpoint(path)
    if kept:
        check_architecture(config, path, name, preset)
    elif not same_architecture(config, get_config(preset)):
        raise CheckpointError(
            f"the download of {name} holds {describe(config)}, but {name} is "
            f"{describe(get_config(preset))}: the link gave another model's weights; "
            f"{outcome}"
        )
