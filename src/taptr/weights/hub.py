"""Weights published on the Hugging Face Hub: where they are, and how a file is had.

`weights_path` reads a published file from the local Hub cache, without a request, and
otherwise (not offline) asks the Hub once and downloads it through ``huggingface_hub``
after a one-line notice of its licence. The transfer is bounded (`taptr.weights.transfer`): the
Hub's name must resolve and a connection open within 2 s
(`taptr.weights.transfer.reach_seconds`), so that an offline machine falls back at once, and the
Hub answer within ``TAPTR_DOWNLOAD_TIMEOUT`` seconds (default `PROBE_TIMEOUT`); the
download must keep up ``TAPTR_DOWNLOAD_MIN_RATE``; a declared or streamed size above what a
release of the weights holds (`taptr.weights.drive.release_bytes`) is refused before the
rest is written. A cached file that cannot be the weights (a web page, a size no release
has) is moved aside with one line and fetched again; one whose SHA-256 is not the
published one is deleted from the cache.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from taptr.messages import install_line
from taptr.weights import transfer
from taptr.weights.checkpoint import CheckpointError
from taptr.weights.drive import IDEA_LICENCE, kept_problem, release_bytes, set_aside

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

PROBE_TIMEOUT = 5.0
"""Seconds to wait for the Hub before falling back (one attempt; ``TAPTR_DOWNLOAD_TIMEOUT``)."""

_SHA256 = re.compile(r"^[0-9a-f]{64}$")
_TRUE = {"1", "on", "yes", "true"}


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


def missing_message(name: str, entry: HubWeights, cache: str, reason: str) -> str:
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
    is deleted from the cache). A cached file that cannot be the weights is moved aside
    and fetched again.

    Args:
        name: a key of `WEIGHTS`.
        cache_dir: Hugging Face cache folder (default: the Hub's, ``HF_HUB_CACHE``).

    Raises:
        KeyError: ``name`` is not published weights.
        FileNotFoundError: not cached and offline (or the Hub could not be reached, or the
            download failed, was too slow or too large); says which file to download and
            where to put it.
        ModuleNotFoundError: ``huggingface_hub`` is missing (the ``hub`` extra).
        CheckpointError: the file does not have its SHA-256.
    """
    entry = WEIGHTS[name]
    try:
        from huggingface_hub import constants
    except ImportError:
        raise ModuleNotFoundError(
            f"{name} is fetched with huggingface_hub: {install_line('hub')}, or download "
            f"{entry.url} yourself and pass the file's path"
        ) from None
    cache = Path(cache_dir) if cache_dir is not None else None
    path = _cached(name, entry, cache)
    if path is not None:
        _check_sha256(path, name, entry.sha256)
        return path
    folder = str(cache or constants.HF_HUB_CACHE)
    if hub_offline():
        reason = "downloads are disabled (HF_HUB_OFFLINE=1)"
        raise FileNotFoundError(missing_message(name, entry, folder, reason))
    return _download(name, entry, cache, folder)


def _cached(name: str, entry: HubWeights, cache: Path | None) -> Path | None:
    """The cached file, or None; a cached file that cannot be the weights is moved aside."""
    from huggingface_hub import hf_hub_download

    try:
        path = Path(
            hf_hub_download(entry.repo_id, entry.filename, cache_dir=cache, local_files_only=True)
        )
    except Exception:
        return None
    if not path.is_file():
        return None
    problem = kept_problem(path, entry.preset)
    if problem is None:
        return path
    # the snapshot's name is a link to the blob that holds the bytes: both go
    blob = path.resolve()
    set_aside(blob, problem, name)
    path.unlink(missing_ok=True)
    return None


def _download(name: str, entry: HubWeights, cache: Path | None, folder: str) -> Path:
    """One probe of the Hub, then the bounded download and its SHA-256 check."""
    from huggingface_hub import hf_hub_url

    # read now: huggingface_hub reads HF_ENDPOINT once, at its import
    endpoint = os.environ.get("HF_ENDPOINT") or None
    url = hf_hub_url(entry.repo_id, entry.filename, endpoint=endpoint)
    seconds = transfer.answer_seconds(PROBE_TIMEOUT)
    try:
        metadata = _probe(url, endpoint, seconds)
    except Exception as error:
        reason = f"the Hub could not be reached ({transfer.short_reason(error)})"
        raise FileNotFoundError(missing_message(name, entry, folder, reason)) from None
    most = release_bytes(entry.preset)[1]
    if metadata.size is not None and metadata.size > most:
        reason = (
            f"the download was refused: the Hub declares {metadata.size:,} bytes, more than a "
            f"release of the weights holds ({most:,}); nothing was kept"
        )
        raise FileNotFoundError(missing_message(name, entry, folder, reason))
    logger.warning(
        "downloading %s weights (%s) from %s: %s, see https://huggingface.co/%s",
        entry.title,
        entry.filename,
        url,
        entry.licence,
        entry.repo_id,
    )
    path = _transfer(name, entry, cache, endpoint, seconds, folder)
    hub_digest = (metadata.etag or "").lower()
    _check_sha256(path, name, entry.sha256 or (hub_digest if _SHA256.match(hub_digest) else None))
    return path


def _probe(url: str, endpoint: str | None, seconds: float) -> Any:
    """The file's metadata, once the Hub's name resolved and the Hub answered in time."""
    from huggingface_hub import get_hf_file_metadata

    transfer.reach(url, transfer.reach_seconds())
    # a single request: hf_hub_download alone retries for ~25 s
    return transfer.within(
        seconds,
        lambda: get_hf_file_metadata(url, timeout=seconds, endpoint=endpoint),
        "the Hub did not answer",
    )


def _transfer(
    name: str,
    entry: HubWeights,
    cache: Path | None,
    endpoint: str | None,
    seconds: float,
    folder: str,
) -> Path:
    """``hf_hub_download``, watched: too slow or too large stops it (`taptr.weights.transfer`)."""
    from huggingface_hub import constants, hf_hub_download

    watch = transfer.Watch(
        f"the download of {name}",
        release_bytes(entry.preset)[1],
        seconds,
        transfer.least_rate(),
        constants.DOWNLOAD_CHUNK_SIZE,
    )
    stop = threading.Event()
    bar = _watched_bar(watch, stop)
    try:
        return Path(
            transfer.watched(
                lambda: hf_hub_download(
                    entry.repo_id,
                    entry.filename,
                    cache_dir=cache,
                    endpoint=endpoint,
                    etag_timeout=seconds,
                    tqdm_class=bar,
                ),
                watch,
                stop,
            )
        )
    except transfer.TransferError as error:
        raise FileNotFoundError(missing_message(name, entry, folder, str(error))) from None
    except Exception as error:
        reason = f"the download failed ({transfer.short_reason(error)})"
        raise FileNotFoundError(missing_message(name, entry, folder, reason)) from None


def _watched_bar(watch: transfer.Watch, stop: threading.Event) -> type:
    """A progress bar class for ``hf_hub_download`` that reports to ``watch``.

    Its reports raise `taptr.weights.transfer.TransferError` (ending the download where it is)
    for a size above the watch's bound, and once ``stop`` is set: a download left behind
    as too slow ends at its next chunk.
    """
    from huggingface_hub.utils import tqdm

    class Watched(tqdm):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            watch.progress(0, self.total)

        def update(self, n: float | None = 1) -> bool | None:
            shown = super().update(n)
            if stop.is_set():
                raise transfer.TransferError(f"{watch.what} was stopped")
            watch.progress(int(self.n), self.total)
            return shown

    return Watched


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
