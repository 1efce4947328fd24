"""Named models: published weights, bundled weights, presets, and local checkpoint files.

``from_pretrained(name_or_path)`` (and `resolve_model`, which the predictor uses) accepts,
in this order:

1. a path to a checkpoint file (taptr's format or the authors' release);
2. the name of weights published on the Hugging Face Hub (`WEIGHTS`), fetched through
   ``huggingface_hub``: the local Hub cache is used when it holds the file, offline mode
   (``HF_HUB_OFFLINE=1``) never touches the network, and a SHA-256 in the registry is
   checked when present;
3. the name of weights that ship inside the package (`BUNDLED`);
4. a preset name: the architecture with freshly initialised, untrained weights (a warning
   says so).

Every file is read by the strict, safe loader (`taptr.checkpoint.load_checkpoint`).
Nothing is downloaded at import; a download happens only when a published name is asked
for, it is not cached, and offline mode is off.
"""

from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import torch

from taptr.checkpoint import CheckpointError, load_checkpoint
from taptr.config import PRESETS
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
        sha256: hex digest of the file, checked after download when set.
    """

    repo_id: str
    filename: str
    preset: str
    title: str
    sha256: str | None = None

    @property
    def url(self) -> str:
        """Direct download address of the file."""
        return f"https://huggingface.co/{self.repo_id}/resolve/main/{self.filename}"


# the authors publish both generations in one repository; digests are added once the
# published files are verified, and are checked from then on
WEIGHTS = {
    "taptrv2-official": HubWeights("HYeungLee/TAPTR-Series", "taptrv2.pth", "taptrv2", "TAPTRv2"),
    "taptrv1-official": HubWeights("HYeungLee/TAPTR-Series", "taptrv1.pth", "taptrv1", "TAPTR v1"),
}
"""Weights on the Hugging Face Hub: name → where the file is and what it holds."""

BUNDLED = {"taptr-small-synthetic": ("taptr-small-synthetic.pth", "small")}
"""Weights inside the package: name → (file under ``taptr/weights``, preset it was trained as)."""

DEFAULT_MODEL = "taptr-small-synthetic"

_TRUE = {"1", "on", "yes", "true"}


def bundled_path(name: str) -> Path | None:
    """The file of bundled weights ``name``, or None when it is not installed."""
    filename = BUNDLED[name][0]
    path = Path(str(resources.files("taptr").joinpath("weights", filename)))
    return path if path.is_file() else None


def known_names() -> list[str]:
    """Every name `resolve_model` accepts besides paths."""
    return [*WEIGHTS, *BUNDLED, *PRESETS]


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

    Args:
        name: a key of `WEIGHTS`.
        cache_dir: Hugging Face cache folder (default: the Hub's, ``HF_HUB_CACHE``).

    Raises:
        KeyError: ``name`` is not published weights.
        FileNotFoundError: not cached and offline (or the download failed); says which
            file to download and where to put it.
        ModuleNotFoundError: ``huggingface_hub`` is missing (``pip install 'taptr[hub]'``).
        CheckpointError: the file does not have the registry's SHA-256.
    """
    entry = WEIGHTS[name]
    try:
        from huggingface_hub import constants, hf_hub_download
        from huggingface_hub.errors import LocalEntryNotFoundError
    except ImportError:
        raise ModuleNotFoundError(
            f"{name} is fetched with huggingface_hub: pip install 'taptr[hub]', or download "
            f"{entry.url} yourself and pass the file's path"
        ) from None
    offline = hub_offline()
    cache = str(cache_dir or constants.HF_HUB_CACHE)
    try:
        path = Path(
            hf_hub_download(
                entry.repo_id,
                entry.filename,
                cache_dir=None if cache_dir is None else Path(cache_dir),
                local_files_only=offline,
            )
        )
    except LocalEntryNotFoundError as error:
        reason = (
            "downloads are disabled (HF_HUB_OFFLINE=1)"
            if offline
            else f"could not be downloaded ({str(error).splitlines()[0]})"
        )
        raise FileNotFoundError(_missing_message(name, entry, cache, reason)) from None
    if entry.sha256 is not None:
        found = file_sha256(path)
        if found != entry.sha256.lower():
            raise CheckpointError(
                f"{path} has SHA-256 {found}, but {name} is {entry.sha256}: the file is "
                "corrupt or not the published one; delete it and download it again"
            )
    return path


def _load_published(name: str, cache_dir: str | os.PathLike[str] | None) -> TAPTR:
    entry = WEIGHTS[name]
    if entry.preset not in PRESETS:  # checked first: no download of a file we cannot load
        raise NotImplementedError(
            f"{entry.title} is not supported yet: this version of taptr has no "
            f"{entry.preset!r} architecture to load {entry.filename} into"
        )
    return load_checkpoint(weights_path(name, cache_dir=cache_dir))


def resolve_model(
    name_or_path: str | os.PathLike[str] | None = None,
    *,
    cache_dir: str | os.PathLike[str] | None = None,
) -> TAPTR:
    """Loads a model by path or name, in eval mode on the CPU.

    Args:
        name_or_path: a checkpoint file, a published weights name (`WEIGHTS`), a bundled
            weights name, a preset name (untrained) or None for the default bundled model.
        cache_dir: Hugging Face cache folder for published weights (default: the Hub's).

    Raises:
        FileNotFoundError: neither an existing file nor a known name (lists the names), or
            published weights that are neither cached nor downloadable (says what to do).
        NotImplementedError: published weights of an architecture taptr does not have.
    """
    name = DEFAULT_MODEL if name_or_path is None else str(name_or_path)
    if Path(name).is_file():
        return load_checkpoint(name)
    if name in WEIGHTS:
        return _load_published(name, cache_dir)
    if name in BUNDLED:
        path = bundled_path(name)
        if path is not None:
            return load_checkpoint(path)
        preset = BUNDLED[name][1] if BUNDLED[name][1] in PRESETS else "tiny"
        logger.warning(
            "bundled weights %r are not installed: using the %r preset with UNTRAINED weights, "
            "whose tracks are meaningless",
            name,
            preset,
        )
        return build_model(preset).eval()
    if name in PRESETS:
        logger.warning("preset %r has UNTRAINED weights: its tracks are meaningless", name)
        return build_model(name).eval()
    raise FileNotFoundError(
        f"no checkpoint file or model named {name!r}; known names: {', '.join(known_names())}"
    )


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
        name_or_path: see `resolve_model`; None gives the bundled default model.
        device: where to put the model.
        cache_dir: Hugging Face cache folder for published weights (default: the Hub's).
    """
    return resolve_model(name_or_path, cache_dir=cache_dir).to(device)
