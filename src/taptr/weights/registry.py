"""Named models: published weights, bundled weights, presets, and local checkpoint files.

``from_pretrained(name_or_path)`` (and `load_model`, which the predictor uses) accepts, in
this order:

1. a path to a checkpoint file (taptr's format or the authors' release);
2. the name of weights published on the Hugging Face Hub (`WEIGHTS`), fetched through
   ``huggingface_hub``: the local Hub cache is used when it holds the file, offline mode
   (``HF_HUB_OFFLINE=1``) never touches the network, and a download is checked against a
   SHA-256 (the registry's when set, else the Hub's own for large files);
3. the name of weights the authors host on Google Drive (`MANUAL`: TAPTRv3's two
   checkpoints, `taptr.weights.drive`): read from the weights folder
   (``TAPTR_WEIGHTS_DIR``, default ``~/.cache/taptr/weights``); when missing, downloaded
   once into it through ``gdown`` (the ``drive`` extra, `taptr.weights.drive_download`)
   after a one-line notice of their licence, and checked before they are kept; without
   gdown or network, one message with the link, the licence and where to put the file;
4. the name of weights that ship inside the package (`BUNDLED`);
5. a preset name: the architecture with freshly initialised, untrained weights (a warning
   says so).

**The default** (no name): the paper's weights, `DEFAULT_MODEL`, from the cache or
downloaded once (after a one-line notice of their licence); when they cannot be had
(offline, no ``huggingface_hub``, the Hub unreachable within `PROBE_TIMEOUT` seconds, a
corrupt download), the bundled `FALLBACK_MODEL` with one warning line saying what to expect
and how to get the paper's weights. A single attempt: no retries.

Every file is read by the strict, safe loader (`taptr.weights.checkpoint.load_checkpoint`); a file
under the name of published or Drive weights must hold the architecture that name promises
(`taptr.weights.identity`): another model's weights are refused with what they are.
Nothing is downloaded at import. ``HF_ENDPOINT`` and ``HF_HUB_OFFLINE`` are read at call time.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import re
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import NamedTuple, TypeVar

import torch

from taptr.config import PRESETS
from taptr.model.build import build_model
from taptr.model.taptr import TAPTR
from taptr.weights.checkpoint import CheckpointError, load_checkpoint_and_threshold
from taptr.weights.drive import MANUAL, check_download, manual_path
from taptr.weights.hub import (  # noqa: F401 (re-exported: taptr.weights.registry is their home for callers)
    PROBE_TIMEOUT,
    WEIGHTS,
    HubWeights,
    file_sha256,
    hub_offline,
    weights_path,
)

logger = logging.getLogger(__name__)

T = TypeVar("T")


BUNDLED = {"taptr-small-synthetic": ("taptr-small-synthetic.pth", "small")}
"""Weights inside the package: name → (file under ``taptr/weights``, preset it was trained as)."""

DEFAULT_MODEL = "taptrv2-official"
"""What runs when no model is named: the paper's weights."""

FALLBACK_MODEL = "taptr-small-synthetic"
"""What runs instead when the default cannot be had."""


class ModelChoice(NamedTuple):
    """A loaded model and where it came from.

    Attributes:
        model: the network, in eval mode on the CPU.
        name: the name or path it was loaded as.
        path: the file it was read from (None for a preset).
        notice: the fallback warning, when the default model could not be had.
        visibility_threshold: the calibrated threshold stored in the file, if any.
    """

    model: TAPTR
    name: str
    path: Path | None
    notice: str | None = None
    visibility_threshold: float | None = None


def _from_file(path: Path, name: str, preset: str | None = None) -> ModelChoice:
    """The model in ``path``; with ``preset`` (named weights), of that architecture only."""
    expected = (name, preset) if preset is not None else None
    model, threshold = load_checkpoint_and_threshold(path, expected=expected)
    return ModelChoice(model, name, Path(path), visibility_threshold=threshold)


def bundled_path(name: str) -> Path | None:
    """The file of bundled weights ``name``, or None when it is not installed."""
    filename = BUNDLED[name][0]
    path = Path(str(resources.files("taptr").joinpath("weights", filename)))
    return path if path.is_file() else None


def known_names() -> list[str]:
    """Every name `resolve_model` accepts besides paths."""
    return [*WEIGHTS, *MANUAL, *BUNDLED, *PRESETS]


def download(name: str, *, cache_dir: str | os.PathLike[str] | None = None) -> Path:
    """The local file of named weights, fetched now when missing (``taptr download``).

    For machines that will be offline later: published weights go to the Hugging Face
    cache, Drive weights to `weights_dir`, each checked as loading checks them (the
    architecture its name promises); bundled weights are already installed.

    Raises:
        KeyError: ``name`` is a preset (no weights) or unknown; the message lists the names.
        FileNotFoundError: the file cannot be had (see `weights_path`, `manual_path`).
        CheckpointError: the file is not what its name says.
    """
    if name in WEIGHTS:
        path = _published_path(name, cache_dir)
        check_download(path, name, WEIGHTS[name].preset, kept=True)
        return path
    if name in MANUAL:
        path = manual_path(name)
        check_download(path, name, MANUAL[name].preset, kept=True)
        return path
    if name in BUNDLED:
        path = bundled_path(name)
        if path is None:
            raise FileNotFoundError(f"the bundled weights {name!r} are not installed")
        return path
    names = ", ".join([*WEIGHTS, *MANUAL, *BUNDLED])
    what = "a preset: untrained, it has no weights" if name in PRESETS else "not a known name"
    raise KeyError(f"{name!r} is {what}; named weights: {names}")


def _first_line(error: BaseException) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def _published_path(name: str, cache_dir: str | os.PathLike[str] | None) -> Path:
    entry = WEIGHTS[name]
    if entry.preset not in PRESETS:  # checked first: no download of a file we cannot load
        raise NotImplementedError(
            f"{entry.title} is not supported yet: this version of taptr has no "
            f"{entry.preset!r} architecture to load {entry.filename} into"
        )
    return weights_path(name, cache_dir=cache_dir)


def fallback_notice(reason: str) -> str:
    """The one line said when the default model falls back to the bundled one.

    It asks for ``pip install huggingface_hub`` (what the ``hub`` extra adds: it installs from a
    checkout and from the package index alike) only when ``huggingface_hub`` is missing.
    """
    entry = WEIGHTS[DEFAULT_MODEL]
    missing = importlib.util.find_spec("huggingface_hub") is None
    install = "pip install huggingface_hub && " if missing else ""
    return (
        f"the paper's weights ({DEFAULT_MODEL}) are not available ({reason}); using the "
        f"bundled {FALLBACK_MODEL}, trained on synthetic videos: its tracks on real "
        f"footage will be rough. Get the paper's weights with: {install}"
        f"hf download {entry.repo_id} {entry.filename}"
    )


Read = Callable[[Path, str, "str | None"], T]
"""Reads a found file: (file, name it was asked as, preset its name promises or None) → T."""
Untrained = Callable[[str, str], T]
"""Stands in untrained weights: (name asked, preset to build) → T."""


def resolve_weights(
    name_or_path: str | os.PathLike[str] | None,
    read: Read[T],
    untrained: Untrained[T],
    *,
    cache_dir: str | os.PathLike[str] | None = None,
) -> tuple[T, str | None]:
    """Finds a name's weights in `load_model`'s order and hands the file to ``read``.

    The one place the order lives: loading a model (`load_model`) and reading what a model
    is without building it (`taptr.corpus.model_facts`) both go through it.

    Returns:
        What ``read`` (or ``untrained``) made, and the fallback notice when the default
        model could not be had (it is also logged once).

    Raises:
        FileNotFoundError: neither an existing file nor a known name (lists the names),
            named published weights that are neither cached nor downloadable, or
            hand-downloaded weights not in `weights_dir` (says where to get them).
        NotImplementedError: published weights of an architecture taptr does not have.
    """
    if name_or_path is None:
        try:
            path = _published_path(DEFAULT_MODEL, cache_dir)
            return read(path, DEFAULT_MODEL, WEIGHTS[DEFAULT_MODEL].preset), None
        except (FileNotFoundError, ModuleNotFoundError, CheckpointError) as error:
            notice = fallback_notice(_reason(error))
        logger.warning(notice)
        return _bundled(FALLBACK_MODEL, read, untrained), notice
    name = str(name_or_path)
    if Path(name).is_file():
        return read(Path(name), name, None), None
    if name in WEIGHTS:
        return _kept(read, _published_path(name, cache_dir), name, WEIGHTS[name].preset), None
    if name in MANUAL:
        return _kept(read, manual_path(name), name, MANUAL[name].preset), None
    if name in BUNDLED:
        return _bundled(name, read, untrained), None
    if name in PRESETS:
        logger.warning("preset %r has UNTRAINED weights: its tracks are meaningless", name)
        return untrained(name, name), None
    raise FileNotFoundError(
        f"no checkpoint file or model named {name!r}; known names: {', '.join(known_names())}"
    )


def load_model(
    name_or_path: str | os.PathLike[str] | None = None,
    *,
    cache_dir: str | os.PathLike[str] | None = None,
) -> ModelChoice:
    """Loads a model by path or name, in eval mode on the CPU, and says where it came from.

    Args:
        name_or_path: a checkpoint file, a published weights name (`WEIGHTS`), a
            hand-downloaded weights name (`MANUAL`), a bundled weights name, a preset name
            (untrained), or None for the default: the paper's weights, else the bundled
            model with one warning (see the module docstring).
        cache_dir: Hugging Face cache folder for published weights (default: the Hub's).

    Raises:
        FileNotFoundError, NotImplementedError: as `resolve_weights`.
    """
    choice, notice = resolve_weights(name_or_path, _from_file, _untrained, cache_dir=cache_dir)
    return choice._replace(notice=notice)


def _untrained(name: str, preset: str) -> ModelChoice:
    return ModelChoice(build_model(preset).eval(), name, None)


def _kept(read: Read[T], path: Path, name: str, preset: str) -> T:
    """``read`` of the file taptr keeps for ``name``; a refusal says what to delete."""
    try:
        return read(path, name, preset)
    except CheckpointError as error:
        if "delete it" in str(error):
            raise
        raise CheckpointError(
            f"{error}; {path} is taptr's copy of {name}: delete it and taptr fetches it again"
        ) from None


def resolve_model(
    name_or_path: str | os.PathLike[str] | None = None,
    *,
    cache_dir: str | os.PathLike[str] | None = None,
) -> TAPTR:
    """The model of `load_model` alone."""
    return load_model(name_or_path, cache_dir=cache_dir).model


def _reason(error: BaseException) -> str:
    """The short cause of a failed fetch, for the fallback line."""
    if isinstance(error, ModuleNotFoundError):
        return "huggingface_hub is not installed"
    text = str(error)
    if isinstance(error, CheckpointError):  # a corrupt download, or another model's file
        return "the download was corrupt" if "SHA-256" in text else _first_line(error)
    if "HF_HUB_OFFLINE" in text:
        return "not in the Hugging Face cache and HF_HUB_OFFLINE=1"
    found = re.search(
        r"and (the Hub could not be reached|the download (?:failed|was refused)"
        r"|the download of \S+ was (?:stopped|refused))",
        text,
    )
    return f"not in the Hugging Face cache and {found.group(1)}" if found else _first_line(error)


def _bundled(name: str, read: Read[T], untrained: Untrained[T]) -> T:
    path = bundled_path(name)
    if path is not None:
        return read(path, name, None)
    preset = BUNDLED[name][1] if BUNDLED[name][1] in PRESETS else "tiny"
    logger.warning(
        "bundled weights %r are not installed: using the %r preset with UNTRAINED weights, "
        "whose tracks are meaningless",
        name,
        preset,
    )
    return untrained(name, preset)


def from_pretrained(
    name_or_path: str | os.PathLike[str] | None = None,
    *,
    device: str | torch.device = "cpu",
    cache_dir: str | os.PathLike[str] | None = None,
) -> TAPTR:
    """A ready model (eval mode) from a checkpoint file or a name.

    ``taptr.from_pretrained("taptrv2-official")`` loads the authors' released TAPTRv2
    (from the Hugging Face cache, downloading it once when allowed).

    Args:
        name_or_path: see `load_model`; None gives the default model (the paper's weights,
            else the bundled model with a warning).
        device: where to put the model.
        cache_dir: Hugging Face cache folder for published weights (default: the Hub's).
    """
    return resolve_model(name_or_path, cache_dir=cache_dir).to(device)
