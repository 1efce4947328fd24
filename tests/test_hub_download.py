"""The default model's download path, end to end, against a fake Hub on 127.0.0.1.

A small HTTP server answers like the Hub's ``resolve`` endpoint (``HEAD`` with the
commit, ETag and size headers, ``GET`` with the bytes); ``HF_ENDPOINT`` points at it.
Nothing leaves the machine.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest

from taptr.weights import registry
from taptr.weights.checkpoint import CheckpointError, save_checkpoint

pytest.importorskip("huggingface_hub")

COMMIT = "89abcdef0123456789abcdef0123456789abcdef"
RESOLVE = "/HYeungLee/TAPTR-Series/resolve/main/taptrv2.pth"


class FakeHub:
    """Serves one file at the Hub's address of taptrv2.pth and counts the requests.

    Args:
        content: the file's bytes.
        etag: its digest as the Hub states it (default: the content's).
        declared: the size its HEAD states (default: the content's).
        trickle: seconds between single bytes of the file, for ``trickle_for`` seconds.
        trickle_for: how long it trickles before it sends the rest.
    """

    def __init__(
        self,
        content: bytes,
        etag: str | None = None,
        declared: int | None = None,
        trickle: float | None = None,
        trickle_for: float = 5.0,
    ) -> None:
        self.content = content
        self.etag = etag or hashlib.sha256(content).hexdigest()
        self.declared, self.trickle, self.trickle_for = declared, trickle, trickle_for
        self.requests: list[str] = []
        self.closing = threading.Event()
        hub_self = self

        class Handler(BaseHTTPRequestHandler):
            def do_HEAD(self):
                hub_self.requests.append("HEAD")
                self._headers(hub_self.declared)

            def do_GET(self):
                hub_self.requests.append("GET")
                if self._headers():
                    with contextlib.suppress(OSError):  # a client that gave up
                        self._body()

            def _body(self) -> None:
                data, until = hub_self.content, time.monotonic() + hub_self.trickle_for
                while hub_self.trickle and data and time.monotonic() < until:
                    if hub_self.closing.wait(hub_self.trickle):
                        return
                    self.wfile.write(data[:1])
                    self.wfile.flush()
                    data = data[1:]
                self.wfile.write(data)

            def _headers(self, declared: int | None = None) -> bool:
                if self.path.split("?")[0] != RESOLVE:
                    self.send_response(404)
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return False
                self.send_response(200)
                self.send_header("X-Repo-Commit", COMMIT)
                self.send_header("ETag", f'"{hub_self.etag}"')
                self.send_header("X-Linked-Etag", f'"{hub_self.etag}"')
                size = len(hub_self.content) if declared is None else declared
                self.send_header("Content-Length", str(size))
                self.end_headers()
                return True

            def log_message(self, *args):
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.closing.set()
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def online(monkeypatch, tmp_path) -> Path:
    """Online mode (the suite runs offline) with an empty cache of our own."""
    from huggingface_hub import constants

    monkeypatch.setenv("HF_HUB_OFFLINE", "0")
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", False)
    cache = tmp_path / "hub-cache"
    monkeypatch.setenv("HF_HUB_CACHE", str(cache))
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(cache))
    return cache


def serve(monkeypatch, content: bytes, etag: str | None = None, **options) -> FakeHub:
    fake = FakeHub(content, etag, **options)
    monkeypatch.setenv("HF_ENDPOINT", fake.url)
    return fake


def test_default_downloads_once_then_reads_the_cache_and_works_offline(
    online, monkeypatch, official_checkpoint, caplog
):
    fake = serve(monkeypatch, official_checkpoint.read_bytes())
    try:
        with caplog.at_level(logging.WARNING, logger="taptr.weights.registry"):
            choice = registry.load_model(None, cache_dir=online)
        assert (choice.name, choice.notice) == ("taptrv2-official", None)
        assert choice.model.config.d_model == 256 and not choice.model.training
        assert fake.requests.count("GET") == 1
        assert "IDEA License 1.0, non-commercial" in caplog.text  # said before the download
        assert choice.path is not None and online in choice.path.parents
        # second call: the cache answers, no request at all
        before = len(fake.requests)
        assert registry.weights_path("taptrv2-official", cache_dir=online) == choice.path
        assert len(fake.requests) == before
    finally:
        fake.close()
    # offline, with the server gone: the cache only
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    assert registry.weights_path("taptrv2-official", cache_dir=online) == choice.path


def test_corrupt_download_is_rejected_and_removed(online, monkeypatch, tiny_model, tmp_path):
    good = save_checkpoint(tiny_model, tmp_path / "good.pth").read_bytes()
    fake = serve(monkeypatch, good[:-100] + b"x" * 100, etag=hashlib.sha256(good).hexdigest())
    try:
        with pytest.raises(CheckpointError, match="corrupt"):
            registry.weights_path("taptrv2-official", cache_dir=online)
        assert not any(p.is_file() for p in online.rglob("taptrv2.pth"))
        # the default falls back instead, and says why
        choice = registry.load_model(None, cache_dir=online)
        assert choice.name == "taptr-small-synthetic" and "corrupt" in choice.notice
    finally:
        fake.close()


def test_unreachable_hub_falls_back_at_once_with_one_warning(online, monkeypatch, caplog):
    with socket.socket() as probe:  # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    monkeypatch.setenv("HF_ENDPOINT", f"http://127.0.0.1:{port}")
    started = time.perf_counter()
    with caplog.at_level(logging.WARNING):
        choice = registry.load_model(None, cache_dir=online)
    assert time.perf_counter() - started < registry.PROBE_TIMEOUT  # one attempt, no retry storm
    assert choice.name == "taptr-small-synthetic" and choice.model.config.d_model == 64
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and warnings[0].getMessage() == choice.notice
    assert "\n" not in choice.notice
    assert "trained on synthetic videos:" in choice.notice
    assert "hf download HYeungLee/TAPTR-Series taptrv2.pth" in choice.notice
    assert "the Hub could not be reached" in choice.notice


def test_offline_without_cache_falls_back_and_names_the_reason(monkeypatch, caplog):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with caplog.at_level(logging.WARNING):
        choice = registry.load_model(None)
    assert choice.name == "taptr-small-synthetic"
    assert "HF_HUB_OFFLINE=1" in choice.notice
    # huggingface_hub is installed here: the hint does not ask to install it again
    assert "pip install" not in choice.notice
    assert choice.notice.endswith("with: hf download HYeungLee/TAPTR-Series taptrv2.pth")


def test_missing_huggingface_hub_falls_back(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "huggingface_hub", None)
    choice = registry.load_model(None)
    assert "huggingface_hub is not installed" in choice.notice
    # what the extra adds, named so that it installs from a checkout and from the index alike
    assert "pip install huggingface_hub && hf download" in choice.notice
    assert "taptr[hub]" not in choice.notice


def test_an_explicit_choice_says_nothing(caplog):
    with caplog.at_level(logging.WARNING):
        choice = registry.load_model("taptr-small-synthetic")
    assert choice.notice is None and not caplog.records


def test_the_command_line_warns_once_and_only_for_the_default(tmp_path, caplog):
    from taptr.cli.main import main
    from taptr.io.video import write_video

    clip = write_video(tmp_path / "clip.mp4", np.full((6, 32, 48, 3), 90, np.uint8), fps=6)
    with caplog.at_level(logging.WARNING):
        assert main(["track", str(clip), "--grid", "2", "--out", str(tmp_path / "a")]) == 0
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "the paper's weights" in warnings[0].getMessage()
    caplog.clear()
    chosen = ["--checkpoint", "taptr-small-synthetic", "--out", str(tmp_path / "b")]
    with caplog.at_level(logging.WARNING):
        assert main(["track", str(clip), "--grid", "2", *chosen]) == 0
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_warnings_are_prefixed_on_the_command_line():
    from taptr.cli.main import LevelFormatter

    record = logging.LogRecord("taptr", logging.WARNING, __file__, 1, "rough tracks", None, None)
    assert LevelFormatter().format(record) == "taptr: warning: rough tracks"
    record.levelno = logging.INFO
    assert LevelFormatter().format(record) == "rough tracks"


# -- issue 45: a Hub that misbehaves ends in seconds ---------------------------------------


def test_a_hub_declaring_far_more_than_the_release_is_refused_before_the_transfer(
    online, monkeypatch, official_checkpoint
):
    fake = serve(monkeypatch, official_checkpoint.read_bytes(), declared=2 * 1024**3)
    try:
        with pytest.raises(FileNotFoundError) as raised:
            registry.weights_path("taptrv2-official", cache_dir=online)
    finally:
        fake.close()
    message = str(raised.value)
    assert "the download was refused: the Hub declares 2,147,483,648 bytes" in message
    assert fake.requests == ["HEAD"]  # nothing fetched
    # the default falls back at once and says why
    fake = serve(monkeypatch, official_checkpoint.read_bytes(), declared=2 * 1024**3)
    try:
        choice = registry.load_model(None, cache_dir=online)
    finally:
        fake.close()
    assert choice.name == "taptr-small-synthetic" and "the download was refused" in choice.notice


def test_a_trickling_hub_is_stopped_by_the_least_rate(online, monkeypatch, official_checkpoint):
    monkeypatch.setenv("TAPTR_DOWNLOAD_TIMEOUT", "0.5")
    monkeypatch.setenv("TAPTR_DOWNLOAD_MIN_RATE", "64M")  # the Hub reports every 10 MB
    fake = serve(monkeypatch, official_checkpoint.read_bytes(), trickle=0.01, trickle_for=8.0)
    started = time.perf_counter()
    try:
        with pytest.raises(FileNotFoundError) as raised:
            registry.weights_path("taptrv2-official", cache_dir=online)
    finally:
        fake.close()
    assert time.perf_counter() - started < 4.0
    message = str(raised.value)
    assert "the download of taptrv2-official was stopped" in message
    assert "TAPTR_DOWNLOAD_MIN_RATE" in message
    assert not any(p.is_file() for p in online.rglob("taptrv2.pth"))
