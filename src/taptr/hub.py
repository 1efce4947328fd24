"""Named models: published weights, bundled weights, presets, and local checkpoint files.

``from_pretrained(name_or_path)`` (and `load_model`, which the predictor uses) accepts, in
this order:

1. a path to a checkpoint file (taptr's format or the authors' release);
2. the name of weights published on the Hugging Face Hub (`WEIGHTS`), fetched through
   ``huggingface_hub``: the local Hub cache is used when it holds the file, offline mode
   (``HF_HUB_OFFLINE=1``) never touches the network, and a download is checked against a
   SHA-256 (the registry's when set, else the Hub's own for large files);
3. the name of weights the authors host on Google Drive (`MANUAL`: TAPTRv3's two
   checkpoints, `taptr.drive_weights`): read from the weights folder
   (``TAPTR_WEIGHTS_DIR``, default ``~/.cache/taptr/weights``);
   when missing, downloaded once into it through ``gdown`` (``pip install 'taptr[drive]'``,
   `taptr.drive`) after a one-line notice of their licence, and checked before they are
   kept; without gdown or network, one message with the link, the licence and where to
   put the file;
4. the name of weights that ship inside the package (`BUNDLED`);
5. a preset name: the architecture with freshly initialised, untrained weights (a warning
   says so).

**The default** (no name): the paper's weights, `DEFAULT_MODEL`, from the cache or
downloaded once (after a one-line notice of their licence); when they cannot be had
(offline, no ``huggingface_hub``, the Hub unreachable within `PROBE_TIMEOUT` seconds, a
corrupt download), the bundled `FALLBACK_MODEL` with one warning line saying what to expect
and how to get the paper's weights. A single attempt: no retries.

Every file is read by the strict, safe loader (`taptr.checkpoint.load_checkpoint`); a file
under the name of published or Drive weights must hold the architecture that name promises
(`taptr.checkpoint_identity`): another model's weights are refused with what they are.
Nothing is downloaded at import. ``HF_ENDPOINT`` and ``HF_HUB_OFFLINE`` are read at call time.
"""

from __future__ import annotations

import hashlib
import importlib.util
import logging
import os
import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import NamedTuple

import torch

from taptr.checkpoint import CheckpointError, load_checkpoint_and_threshold
from taptr.config import PRESETS
from taptr.drive_weights import (
    IDEA_LICENCE,
    MANUAL,
    check_download,
    manual_path,
)
from taptr.model.build import build_model
from taptr.model.taptr import TAPTR

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class HubWeights:
    """Weights published as one file of a Hugging Face Hub repository.

    Attributes:
        repo_id: the Hub repository, ``owner/name``.
        filename: the file inside it.
        preset: the architecture the file holds (a key of `taptr.config.PRESETS`).
        title: the model's name in messages.
        licence: the weights' licence, named before a download.
        sha256: hex digest of the file, checked after download when set.
    """

    repo_id: str
    filename: str
    preset: str
    title: str
    licence: str
    sha256: str | None = None

    @property
    def url(self) -> str:
        """Direct download address of the file."""
        return f"https://huggingface.co/{self.repo_id}/resolve/main/{self.filename}"


# the authors publish both generations in one repository; digests are added once the
# published files are verified, and are checked from then on
WEIGHTS = {
    "taptrv2-official": HubWeights(
        "HYeungLee/TAPTR-Series", "taptrv2.pth", "taptrv2", "TAPTRv2", IDEA_LICENCE
    ),
    "taptrv1-official": HubWeights(
        "HYeungLee/TAPTR-Series", "taptrv1.pth", "taptrv1", "TAPTR v1", IDEA_LICENCE
    ),
}
"""Weights on the Hugging Face Hub: name → where the file is and what it holds."""


BUNDLED = {"taptr-small-synthetic": ("taptr-small-synthetic.pth", "small")}
"""Weights inside the package: name → (file under ``taptr/weights``, preset it was trained as)."""

DEFAULT_MODEL = "taptrv2-official"
"""What runs when no model is named: the paper's weights."""

FALLBACK_MODEL = "taptr-small-synthetic"
"""What runs instead when the default cannot be had."""

PROBE_TIMEOUT = 5.0
"""Seconds to wait for the Hub before falling back (one attempt)."""

_SHA256 = re.compile(r"^[0-9a-f]{64}$")


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


def _from_file(path: str | os.PathLike[str], name: str, preset: str | None = None) -> ModelChoice:
    """The model in ``path``; with ``preset`` (named weights), of that architecture only."""
    expected = (name, preset) if preset is not None else None
    model, threshold = load_checkpoint_and_threshold(path, expected=expected)
    return ModelChoice(model, name, Path(path), visibility_threshold=threshold)


_TRUE = {"1", "on", "yes", "true"}


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
        check_download(path, name, WEIGHTS[name].preset)
        return path
    if name in MANUAL:
        path = manual_path(name)
        check_download(path, name, MANUAL[name].preset)
        return path
    if name in BUNDLED:
        path = bundled_path(name)
        if path is None:
            raise FileNotFoundError(f"the bundled weights {name!r} are not installed")
        return path
    names = ", ".join([*WEIGHTS, *MANUAL, *BUNDLED])
    what = "a preset: untrained, it has no weights" if name in PRESETS else "not a known name"
    raise KeyError(f"{name!r} is {what}; named weights: {names}")


def hub_offline() -> bool:
    """Whether Hub downloads are disabled (``HF_HUB_OFFLINE``, read now, not at import)."""
    if os.environ.get("HF_HUB_OFFLINE", "").strip().lower() in _TRUE:
        return True
    try:
        from huggingface_hub import constants
    except ImportError:
        return False
    return bool(constants.HF_HUB_OFFLINE)


def file_sha256(path: str | os.PathLike[str]) -> str:
    """Hex SHA-256 of a file, read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with Path(path).open("rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _missing_message(name: str, entry: HubWeights, cache: str, reason: str) -> str:
    """What to download and where to put it, for a published file that cannot be had."""
    folder = Path(cache) / f"models--{entry.repo_id.replace('/', '--')}"
    digest = f" (SHA-256 {entry.sha256})" if entry.sha256 else ""
    return (
        f"{name}: {entry.filename} is not in the Hugging Face cache ({cache}) and {reason}. "
        f"Download {entry.url}{digest}, then either pass its path "
        f'(taptr.from_pretrained("/path/to/{entry.filename}"), or --checkpoint on the command '
        f"line), or fill the cache on a machine with network access "
        f"(`hf download {entry.repo_id} {entry.filename}`) and copy its folder {folder.name} "
        f"to {folder}"
    )


def weights_path(name: str, *, cache_dir: str | os.PathLike[str] | None = None) -> Path:
    """The local file of published weights ``name``, downloaded only when needed and allowed.

    The cache is read first, without a request. Otherwise (and not offline) the Hub is asked
    once, within `PROBE_TIMEOUT` seconds, then the file is downloaded with a progress bar
    after a one-line notice of its licence, and checked against its SHA-256 (a corrupt file
    is deleted from the cache).

    Args:
        name: a key of `WEIGHTS`.
        cache_dir: Hugging Face cache folder (default: the Hub's, ``HF_HUB_CACHE``).

    Raises:
        KeyError: ``name`` is not published weights.
        FileNotFoundError: not cached and offline (or the Hub could not be reached, or the
            download failed); says which file to download and where to put it.
        ModuleNotFoundError: ``huggingface_hub`` is missing (``pip install 'taptr[hub]'``).
        CheckpointError: the file does not have its SHA-256.
    """
    entry = WEIGHTS[name]
    try:
        from huggingface_hub import constants, hf_hub_download
    except ImportError:
        raise ModuleNotFoundError(
            f"{name} is fetched with huggingface_hub: pip install 'taptr[hub]', or download "
            f"{entry.url} yourself and pass the file's path"
        ) from None
    cache = Path(cache_dir) if cache_dir is not None else None
    try:
        path = Path(
            hf_hub_download(entry.repo_id, entry.filename, cache_dir=cache, local_files_only=True)
        )
    except Exception:
        path = None
    if path is not None:
        _check_sha256(path, name, entry.sha256)
        return path
    folder = str(cache or constants.HF_HUB_CACHE)
    if hub_offline():
        reason = "downloads are disabled (HF_HUB_OFFLINE=1)"
        raise FileNotFoundError(_missing_message(name, entry, folder, reason))
    return _download(name, entry, cache, folder)


def _download(name: str, entry: HubWeights, cache: Path | None, folder: str) -> Path:
    """One probe of the Hub, then the download and its SHA-256 check."""
    from huggingface_hub import get_hf_file_metadata, hf_hub_download, hf_hub_url

    # read now: huggingface_hub reads HF_ENDPOINT once, at its import
    endpoint = os.environ.get("HF_ENDPOINT") or None
    url = hf_hub_url(entry.repo_id, entry.filename, endpoint=endpoint)
    try:
        # a single request with a short timeout: hf_hub_download alone retries for ~25 s
        metadata = get_hf_file_metadata(url, timeout=PROBE_TIMEOUT, endpoint=endpoint)
    except Exception as error:
        reason = f"the Hub could not be reached ({_first_line(error)})"
        raise FileNotFoundError(_missing_message(name, entry, folder, reason)) from None
    logger.warning(
        "downloading %s weights (%s) from %s: %s, see https://huggingface.co/%s",
        entry.title,
        entry.filename,
        url,
        entry.licence,
        entry.repo_id,
    )
    try:
        path = Path(
            hf_hub_download(
                entry.repo_id,
                entry.filename,
                cache_dir=cache,
                endpoint=endpoint,
                etag_timeout=PROBE_TIMEOUT,
            )
        )
    except Exception as error:
        reason = f"the download failed ({_first_line(error)})"
        raise FileNotFoundError(_missing_message(name, entry, folder, reason)) from None
    hub_digest = (metadata.etag or "").lower()
    _check_sha256(path, name, entry.sha256 or (hub_digest if _SHA256.match(hub_digest) else None))
    return path


def _check_sha256(path: Path, name: str, expected: str | None) -> None:
    """Deletes ``path`` from the cache and raises when its digest is not ``expected``."""
    if expected is None:
        return
    found = file_sha256(path)
    if found != expected.lower():
        blob = path.resolve()
        path.unlink(missing_ok=True)
        blob.unlink(missing_ok=True)
        raise CheckpointError(
            f"{path} has SHA-256 {found}, but {name} is {expected}: the file is corrupt or "
            "not the published one; it was deleted from the cache, try again"
        )


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

    It asks for ``pip install 'taptr[hub]'`` only when ``huggingface_hub`` is missing.
    """
    entry = WEIGHTS[DEFAULT_MODEL]
    install = "" if importlib.util.find_spec("huggingface_hub") else "pip install 'taptr[hub]' && "
    return (
        f"the paper's weights ({DEFAULT_MODEL}) are not available ({reason}); using the "
        f"bundled {FALLBACK_MODEL}, trained on synthetic videos: its tracks on real "
        f"footage will be rough. Get the paper's weights with: {install}"
        f"hf download {entry.repo_id} {entry.filename}"
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
        FileNotFoundError: neither an existing file nor a known name (lists the names),
            named published weights that are neither cached nor downloadable, or
            hand-downloaded weights not in `weights_dir` (says where to get them).
        NotImplementedError: published weights of an architecture taptr does not have.
    """
    if name_or_path is None:
        return _default_model(cache_dir)
    name = str(name_or_path)
    if Path(name).is_file():
        return _from_file(name, name)
    if name in WEIGHTS:
        return _from_file(_published_path(name, cache_dir), name, WEIGHTS[name].preset)
    if name in MANUAL:
        return _from_file(manual_path(name), name, MANUAL[name].preset)
    if name in BUNDLED:
        return _bundled(name)
    if name in PRESETS:
        logger.warning("preset %r has UNTRAINED weights: its tracks are meaningless", name)
        return ModelChoice(build_model(name).eval(), name, None)
    raise FileNotFoundError(
        f"no checkpoint file or model named {name!r}; known names: {', '.join(known_names())}"
    )


def resolve_model(
    name_or_path: str | os.PathLike[str] | None = None,
    *,
    cache_dir: str | os.PathLike[str] | None = None,
) -> TAPTR:
    """The model of `load_model` alone."""
    return load_model(name_or_path, cache_dir=cache_dir).model


def _default_model(cache_dir: str | os.PathLike[str] | None) -> ModelChoice:
    """The paper's weights when they can be had, else the bundled model and one warning."""
    try:
        path = _published_path(DEFAULT_MODEL, cache_dir)
        return _from_file(path, DEFAULT_MODEL, WEIGHTS[DEFAULT_MODEL].preset)
    except (FileNotFoundError, ModuleNotFoundError, CheckpointError) as error:
        reason = _reason(error)
    notice = fallback_notice(reason)
    logger.warning(notice)
    return _bundled(FALLBACK_MODEL)._replace(notice=notice)


def _reason(error: BaseException) -> str:
    """The short cause of a failed fetch, for the fallback line."""
    if isinstance(error, ModuleNotFoundError):
        return "huggingface_hub is not installed"
    text = str(error)
    if isinstance(error, CheckpointError):  # a corrupt download, or another model's file
        return "the download was corrupt" if "SHA-256" in text else _first_line(error)
    if "HF_HUB_OFFLINE" in text:
        return "not in the Hugging Face cache and HF_HUB_OFFLINE=1"
    found = re.search(r"and (the Hub could not be reached|the download failed)", text)
    return f"not in the Hugging Face cache and {found.group(1)}" if found else _first_line(error)


def _bundled(name: str) -> ModelChoice:
    path = bundled_path(name)
    if path is not None:
        return _from_file(path, name)
    preset = BUNDLED[name][1] if BUNDLED[name][1] in PRESETS else "tiny"
    logger.warning(
        "bundled weights %r are not installed: using the %r preset with UNTRAINED weights, "
        "whose tracks are meaningless",
        name,
        preset,
    )
    return ModelChoice(build_model(preset).eval(), name, None)


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
