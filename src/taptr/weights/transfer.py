"""Downloads that end: a bounded wait for the first answer, a least rate, a size bound.

The libraries that fetch weights (``gdown`` for Google Drive, ``huggingface_hub``) time
out only between two bytes: a server that sends one byte every 20 s never trips a 60 s
read timeout, a name that the resolver cannot answer waits on the resolver's own retries
(30-56 s were seen offline), and a response of any size is written to disk in full.
Around them taptr bounds:

- **the first answer**: the server's name must resolve and a connection open within
  `REACH_SECONDS` (`reach`: an offline machine learns it in two seconds, and the default
  model falls back as soon), and the caller bounds its first request by
  ``TAPTR_DOWNLOAD_TIMEOUT`` seconds (`within`), which, when set, bounds both;
- **the rate**: after that many seconds, the bytes received must keep up with
  ``TAPTR_DOWNLOAD_MIN_RATE`` bytes a second on average (`Watch`), counting the bytes a
  library holds before it reports them (`Watch.slack`);
- **the size**: a declared or streamed size above what the file can be (`Watch.most`) is
  refused at the first report, before the rest is written.

A download that breaks a bound is stopped and said in one line naming the variable to
change. The library's own transfer runs in a worker thread (`watched`) that the caller
stops through the library's cancel hook, or, where there is none, leaves behind: it
ends with the connection.
"""

from __future__ import annotations

import os
import socket
import threading
import time
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Generic, TypeVar
from urllib.parse import urlsplit

T = TypeVar("T")

TIMEOUT_VARIABLE = "TAPTR_DOWNLOAD_TIMEOUT"
"""Seconds a server has to answer (and the grace before the least rate applies)."""

RATE_VARIABLE = "TAPTR_DOWNLOAD_MIN_RATE"
"""Least average bytes a second of a download; 0 turns the check off."""

DEFAULT_MIN_RATE = 32 * 1024
"""32 KiB/s: the paper's weights (160 MB) in 83 minutes at worst."""

REACH_SECONDS = 2.0
"""Seconds for a server's name to resolve and a connection to open, unless
``TAPTR_DOWNLOAD_TIMEOUT`` says otherwise: a working network takes a fraction of a second,
and a resolver with no network behind it waits 5 s a try, several tries."""

POLL_SECONDS = 0.05
"""How often a watched transfer is looked at."""

_SUFFIXES = {"K": 1024, "M": 1024**2}

SHORT_REASON_CHARS = 160
"""Longest cause quoted from a library's error (they nest whole reprs of other errors)."""


class TransferError(Exception):
    """A download broke a bound (too slow, too large, no answer); the message says which."""


def answer_seconds(default: float) -> float:
    """Seconds a server has to answer: ``TAPTR_DOWNLOAD_TIMEOUT``, else ``default``.

    Raises:
        ValueError: the variable is not a positive number of seconds.
    """
    text = os.environ.get(TIMEOUT_VARIABLE, "").strip()
    if not text:
        return default
    try:
        seconds = float(text)
    except ValueError:
        seconds = -1.0
    if not 0 < seconds < 10**6:
        raise ValueError(
            f"{TIMEOUT_VARIABLE}={text[:40]!r} is not a number of seconds: write e.g. 10"
        )
    return seconds


def reach_seconds() -> float:
    """Seconds for a name to resolve and a connection to open.

    ``TAPTR_DOWNLOAD_TIMEOUT`` when it is set, else `REACH_SECONDS`.

    Raises:
        ValueError: the variable is not a positive number of seconds.
    """
    return answer_seconds(REACH_SECONDS)


def least_rate() -> float:
    """Least bytes a second: ``TAPTR_DOWNLOAD_MIN_RATE`` (K, M: powers of 1024), else 32K.

    Raises:
        ValueError: the variable is not a number of bytes a second (0 allowed).
    """
    text = os.environ.get(RATE_VARIABLE, "").strip()
    if not text:
        return float(DEFAULT_MIN_RATE)
    scale = _SUFFIXES.get(text[-1:].upper(), 1)
    try:
        rate = float(text[:-1] if scale > 1 else text) * scale
    except ValueError:
        rate = -1.0
    if not 0 <= rate < 2**50:
        raise ValueError(
            f"{RATE_VARIABLE}={text[:40]!r} is not a rate: write bytes a second, optionally "
            "with K or M (e.g. 64K), or 0 to turn the check off"
        )
    return rate


def short_reason(error: BaseException) -> str:
    """The first line of ``error``, cut at a word boundary when long, never mid-word."""
    text = str(error).strip()
    line = text.splitlines()[0] if text else type(error).__name__
    if len(line) <= SHORT_REASON_CHARS:
        return line
    cut = line[:SHORT_REASON_CHARS]
    boundary = max(cut.rfind(mark) for mark in " ,;:()'\"=/")
    return f"{cut[:boundary].rstrip(' ,;:(=/')} ..." if boundary > 0 else f"{cut} ..."


class _InThread(Generic[T]):
    """``call()`` run in a daemon thread, its value or error handed to the caller's thread.

    Attributes:
        done: set once ``call`` has returned or raised.
    """

    def __init__(self, call: Callable[[], T], name: str) -> None:
        self.done = threading.Event()
        self._outcome: dict[str, object] = {}
        threading.Thread(target=self._run, args=(call,), daemon=True, name=name).start()

    def _run(self, call: Callable[[], T]) -> None:
        try:
            self._outcome["value"] = call()
        except BaseException as error:  # handed to the caller's thread
            self._outcome["error"] = error
        self.done.set()

    def result(self) -> T:
        """What ``call`` returned, or its error raised here (once `done` is set)."""
        if "error" in self._outcome:
            raise self._outcome["error"]  # type: ignore[misc]
        return self._outcome["value"]  # type: ignore[return-value]


def within(seconds: float, call: Callable[[], T], late: str) -> T:
    """``call()``, or `TransferError` (``late``) when it has not returned after ``seconds``.

    The call runs in a daemon thread: one stuck in the resolver or on a silent socket is
    left to end with its own timeout, and this returns at once.
    """
    job = _InThread(call, "taptr-download-probe")
    if not job.done.wait(seconds):
        raise TransferError(f"{late} within {seconds:g} s ({TIMEOUT_VARIABLE} sets how long)")
    return job.result()


def reach(url: str, seconds: float) -> None:
    """Resolves ``url``'s host and opens a connection to it within ``seconds``.

    Through the proxy the environment names for it, when there is one (the proxy
    resolves the name then). A host that answers is left at once.

    Raises:
        TransferError: the name does not resolve, nothing answers, or not in time.
    """
    target = _connect_target(url)
    host, port = target
    shown = f"{host}:{port}"
    try:
        within(seconds, lambda: socket.create_connection(target, timeout=seconds).close(), "")
    except TransferError:
        raise TransferError(
            f"{shown} did not answer within {seconds:g} s: offline? ({TIMEOUT_VARIABLE} "
            "sets how long to wait)"
        ) from None
    except socket.gaierror:
        raise TransferError(f"the name {host} does not resolve: offline?") from None
    except OSError as error:
        raise TransferError(f"{shown} cannot be reached ({error.strerror or error})") from None


def _connect_target(url: str) -> tuple[str, int]:
    """(host, port) a request for ``url`` connects to: its proxy's, or its own."""
    parts = urlsplit(url)
    host = parts.hostname or ""
    port = parts.port or (443 if parts.scheme == "https" else 80)
    proxy = urllib.request.getproxies().get(parts.scheme)
    if proxy and not urllib.request.proxy_bypass(host):
        through = urlsplit(proxy if "://" in proxy else f"http://{proxy}")
        return through.hostname or host, through.port or 80
    return host, port


@dataclass
class Watch:
    """What a transfer has done, against its bounds; told by the library's progress reports.

    Attributes:
        what: the download, for messages (``"the download of taptrv3-official"``).
        most: largest size the file can have, in bytes.
        grace: seconds before the least rate applies (the wait for the first answer).
        rate: least average bytes a second after ``grace`` (0: none).
        slack: bytes the library may hold before it reports them (its chunk size).
        clock: the timer (injected by tests).
    """

    what: str
    most: int
    grace: float
    rate: float
    slack: int
    clock: Callable[[], float] = time.monotonic
    received: int = 0
    start: float = field(default=0.0, init=False)

    def __post_init__(self) -> None:
        self.start = self.clock()

    def progress(self, received: int, declared: int | None = None) -> None:
        """Takes a report: bytes so far and the declared size (None: not declared).

        Raises:
            TransferError: either size is above `most`.
        """
        self.received = max(self.received, received)
        for size, how in ((declared, "declares"), (received, "sent")):
            if size is not None and size > self.most:
                raise TransferError(
                    f"{self.what} was refused: the server {how} {size:,} bytes, more than the "
                    f"{self.most:,} the file can hold; nothing was kept"
                )

    def too_slow(self) -> str | None:
        """Why the transfer is too slow to go on, or None while it keeps up."""
        elapsed = self.clock() - self.start
        owed = self.rate * (elapsed - self.grace)
        if self.rate <= 0 or self.received + self.slack >= owed:
            return None
        return (
            f"{self.what} was stopped: {self.received:,} bytes in {elapsed:.0f} s, slower "
            f"than {self.rate:,.0f} bytes a second; nothing was kept (set {RATE_VARIABLE} "
            "lower, e.g. 8K, or 0 to wait however long it takes)"
        )


def watched(transfer: Callable[[], T], watch: Watch, stop: threading.Event) -> T:
    """Runs ``transfer`` in a worker thread until it ends or ``watch`` finds it too slow.

    Args:
        transfer: the library's download; it reports to ``watch`` and ends soon after
            ``stop`` is set where the library can be stopped.
        watch: the bounds.
        stop: set when the transfer must stop (too slow, or Ctrl-C here).

    Raises:
        TransferError: too slow (the transfer's own errors are raised as they are).
    """
    job = _InThread(transfer, "taptr-download")
    try:
        while not job.done.wait(POLL_SECONDS):
            slow = watch.too_slow()
            if slow is not None:
                stop.set()
                job.done.wait(1.0)  # a cancellable library stops within its poll
                raise TransferError(slow)
    except BaseException:
        stop.set()
        raise
    return job.result()
