"""Downloads from Google Drive, where the authors host TAPTRv3's weights.

Drive answers a scripted request for a large file with a confirmation page (a form whose
action and hidden fields make the real download address) instead of the file. taptr asks
Drive once for the file (within `PROBE_TIMEOUT` seconds), lets ``gdown`` read the page
(`gdown.download.get_url_from_gdrive_confirmation`, kept up to date with Drive's pages by
its maintainers) and fetch the file with a progress bar into a hidden temporary next to
its destination (the hidden temporary of `taptr.io.atomic.atomic_path`, which a killed
process leaves for the next download to remove), checks what arrived, and only then
renames it into place: a partial or wrong download never looks complete. The checks are
the caller's (`fetch`'s ``check``): `taptr.weights.registry` refuses web pages, files
smaller than the weights they should hold and another model's weights.

The transfer is bounded (`taptr.weights.transfer`): Drive's name must resolve and a connection
open within seconds (`taptr.weights.transfer.reach_seconds`), Drive answer within
``TAPTR_DOWNLOAD_TIMEOUT`` seconds (default `PROBE_TIMEOUT`), the download keep up
``TAPTR_DOWNLOAD_MIN_RATE`` after that, and its declared or streamed size stay within what
the file can be (``largest``); one that does not is stopped with one line saying why.

Environment, read at call time: ``TAPTR_DRIVE_URL`` replaces ``https://drive.google.com``
(a testing hook: the tests serve a fake Drive on 127.0.0.1); ``TAPTR_OFFLINE=1`` (or
``HF_HUB_OFFLINE=1``) disables every download.
"""

from __future__ import annotations

import logging
import os
import re
import threading
from collections.abc import Callable
from pathlib import Path

from taptr.io.atomic import atomic_path
from taptr.messages import install_line
from taptr.weights import transfer

logger = logging.getLogger(__name__)

DRIVE_URL = "https://drive.google.com"
"""Where Drive answers ``/uc?export=download&id=ID`` (``TAPTR_DRIVE_URL`` replaces it)."""

PROBE_TIMEOUT = 10.0
"""Seconds to wait for Drive's first answer (one attempt; ``TAPTR_DOWNLOAD_TIMEOUT``)."""

READ_TIMEOUT = 60.0
"""Seconds without a byte after which a download is abandoned."""

CHUNK_BYTES = 512 * 1024
"""Bytes gdown reads before it reports progress (its ``CHUNK_SIZE``)."""

MAX_PAGE_BYTES = 1024**2
"""Largest confirmation page read: Drive's are a few kilobytes."""

"""What installs the downloader (gdown)."""

_TRUE = {"1", "on", "yes", "true"}


class DriveError(FileNotFoundError):
    """The file could not be had: no gdown, offline, Drive unreachable or the transfer broke."""


def offline() -> bool:
    """Whether downloads are disabled (``TAPTR_OFFLINE`` or ``HF_HUB_OFFLINE``, read now)."""
    return any(
        os.environ.get(variable, "").strip().lower() in _TRUE
        for variable in ("TAPTR_OFFLINE", "HF_HUB_OFFLINE")
    )


def can_download() -> bool:
    """Whether `fetch` may try: downloads are allowed and gdown is installed."""
    if offline():
        return False
    try:
        import gdown  # noqa: F401
    except ImportError:
        return False
    return True


def file_id(url: str) -> str:
    """The file id of a Drive link (``.../file/d/ID...`` or ``...?id=ID``)."""
    found = re.search(r"/file/d/([-\w]+)|[?&]id=([-\w]+)", url)
    if found is None:
        raise ValueError(f"not a Google Drive file link: {url}")
    return found.group(1) or found.group(2)


def base_url() -> str:
    """Drive's address, or the testing hook's (``TAPTR_DRIVE_URL``), without a final '/'."""
    return (os.environ.get("TAPTR_DRIVE_URL") or DRIVE_URL).rstrip("/")


def fetch(
    url: str,
    destination: Path,
    check: Callable[[Path], None],
    *,
    largest: int,
    announce: Callable[[], None] = lambda: None,
) -> Path:
    """Downloads a Drive file to ``destination``, atomically, after ``check`` accepts it.

    Args:
        url: the Drive link of the file.
        destination: where the file goes; nothing appears there unless ``check`` passes.
        check: raises (a `taptr.weights.checkpoint.CheckpointError`) when the downloaded file is
            not what it should be; it runs on the temporary file.
        largest: bytes the file can have at most: a larger declared or streamed size
            stops the download.
        announce: called once Drive answered, before the transfer (the licence line).

    Raises:
        DriveError: gdown is missing, downloads are disabled, Drive could not be
            reached, did not give the file, or the transfer broke, was too slow or too
            large; the message says which.
    """
    if offline():
        raise DriveError("downloads are disabled (TAPTR_OFFLINE or HF_HUB_OFFLINE)")
    try:
        import gdown
    except ImportError:
        raise DriveError(f"gdown is not installed ({install_line('drive')})") from None
    seconds = transfer.answer_seconds(PROBE_TIMEOUT)
    address = _answer(f"{base_url()}/uc?export=download&id={file_id(url)}", seconds)
    announce()
    watch = transfer.Watch(
        f"the download of {destination.name}", largest, seconds, transfer.least_rate(), CHUNK_BYTES
    )
    with atomic_path(destination) as temporary:
        # gdown writes into our temporary (a stream: no file of its own to leave behind),
        # which a killed process leaves for the next write to remove (`atomic_path`)
        with temporary.open("wb") as stream:
            stop = threading.Event()

            def download() -> object:
                return gdown.download(
                    url=address,
                    output=stream,
                    quiet=False,
                    use_cookies=False,
                    timeout=(seconds, READ_TIMEOUT),
                    log_messages={"start": "", "output": f"To: {destination}\n"},
                    progress=watch.progress,
                    cancel=stop,
                )

            try:
                transfer.watched(download, watch, stop)
            except transfer.TransferError as error:
                raise DriveError(str(error)) from None
            except Exception as error:  # gdown's DownloadError, requests' errors
                raise DriveError(f"the download broke off ({_first_line(error)})") from None
        check(temporary)
    return destination


def _answer(first: str, seconds: float) -> str:
    """The address that serves the file, once Drive answered ``first`` within ``seconds``.

    Raises:
        DriveError: Drive's name does not resolve, Drive does not answer in time, answers
            with an error, or with a page that leads to no file.
    """
    from gdown.download import get_url_from_gdrive_confirmation
    from gdown.exceptions import FileURLRetrievalError

    try:
        transfer.reach(first, transfer.reach_seconds())
        return transfer.within(
            seconds,
            lambda: _file_address(first, get_url_from_gdrive_confirmation, seconds),
            "Drive did not answer",
        )
    except DriveError:
        raise
    except FileURLRetrievalError as error:
        raise DriveError(f"Drive did not give the file ({_first_line(error)})") from None
    except transfer.TransferError as error:
        raise DriveError(f"Drive could not be reached: {error}") from None
    except Exception as error:  # requests' connection errors and timeouts
        raise DriveError(f"Drive could not be reached ({_first_line(error)})") from None


def _file_address(first: str, confirmation: Callable[[str], str], seconds: float) -> str:
    """The address that serves the file: ``first`` itself, or its confirmation page's."""
    import requests

    with requests.get(first, stream=True, timeout=seconds) as response:
        response.raise_for_status()
        if "Content-Disposition" in response.headers:
            return first
        if not response.headers.get("Content-Type", "").startswith("text/html"):
            return first
        page = response.raw.read(MAX_PAGE_BYTES + 1, decode_content=True)
        if len(page) > MAX_PAGE_BYTES:
            raise DriveError(f"Drive answered with a page of more than {MAX_PAGE_BYTES:,} bytes")
        return confirmation(page.decode(response.encoding or "utf-8", errors="replace"))


def _first_line(error: BaseException) -> str:
    """The error's first line, shortened at a word (network errors nest whole reprs)."""
    return transfer.short_reason(error)
