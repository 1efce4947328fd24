"""Downloads from servers that misbehave end in seconds, with one line (issue 45).

Against the fake Drive of `tests.fake_drive` and a fake Hub on 127.0.0.1: a bad file
already at the target is moved aside and fetched again; a server that trickles is stopped
by the least rate (``TAPTR_DOWNLOAD_MIN_RATE``); a declared or streamed size far above the
release's is refused before it is written; a name that does not resolve, or resolves
slowly, fails within ``TAPTR_DOWNLOAD_TIMEOUT``; and the messages say what happened. Most
tests fetch a tiny model registered as Drive weights (``tiny-drive``), so that a bound is
a few megabytes and every test takes a second or two. Nothing leaves the machine.
"""

from __future__ import annotations

import functools
import logging
import socket
import threading
import time
from pathlib import Path

import pytest
import torch

import taptr
from taptr.weights import registry
from taptr.weights.checkpoint import save_checkpoint
from taptr.weights.drive import ManualWeights, release_bytes
from tests.fake_drive import files_in

pytest.importorskip("gdown")

QUICK = "0.5"
"""``TAPTR_DOWNLOAD_TIMEOUT`` of the tests of a slow or silent server."""

HANG = 10.0
"""Seconds a slow resolver takes: the code before issue 45 waited for it."""

TINY_ID = "tiny-drive-id"
TINY = ManualWeights(f"https://drive.google.com/file/d/{TINY_ID}", "tiny.pth", "tiny", "tiny", "")
"""A tiny model registered as Drive weights: its bound (`release_bytes`) is 4.7 MiB."""


@pytest.fixture(scope="module")
def tiny_file(tmp_path_factory) -> bytes:
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("tiny") / "tiny.pth"
    return save_checkpoint(taptr.build_model("tiny"), path).read_bytes()


@pytest.fixture
def weights_folder(weights_folder, monkeypatch) -> Path:
    """The empty weights folder, ``tiny-drive`` registered, answers awaited 3 s.

    3 s is ample on a loaded machine; the tests of a slow server lower it to `QUICK` seconds.
    """
    monkeypatch.setenv("TAPTR_DOWNLOAD_TIMEOUT", "3")
    monkeypatch.setenv("TAPTR_DOWNLOAD_MIN_RATE", "16M")
    monkeypatch.setitem(registry.MANUAL, "tiny-drive", TINY)
    return weights_folder


@pytest.fixture
def fake_drive(fake_drive):
    """Fake Drives that serve the tiny file's id."""
    return functools.partial(fake_drive, ids=(TINY_ID,))


def _timed(call) -> tuple[BaseException | None, float]:
    started = time.perf_counter()
    try:
        call()
    except Exception as error:
        return error, time.perf_counter() - started
    return None, time.perf_counter() - started


# -- a bad file at the target --------------------------------------------------------------


@pytest.mark.parametrize("bad", ["partial", "web page"])
def test_a_bad_file_at_the_target_is_moved_aside_and_fetched_again(
    weights_folder, fake_drive, tiny_file, caplog, bad
):
    weights_folder.mkdir()
    content = tiny_file[:1000] if bad == "partial" else b"<!DOCTYPE html><html>quota</html>"
    (weights_folder / "tiny.pth").write_bytes(content)
    fake = fake_drive(tiny_file)
    with caplog.at_level(logging.WARNING):
        model = taptr.from_pretrained("tiny-drive")
    assert model.config.d_model == 32  # the tiny preset's
    assert (weights_folder / "tiny.pth").read_bytes() == tiny_file  # fetched again
    assert (weights_folder / "tiny.pth.rejected").read_bytes() == content  # kept aside, not lost
    lines = [r.getMessage() for r in caplog.records if "moved aside" in r.getMessage()]
    reason = "a transfer cut short" if bad == "partial" else "a web page (HTML)"
    assert len(lines) == 1 and reason in lines[0] and "fetching it again" in lines[0]
    assert fake.requests == ["/uc", "/download"]


def test_taptr_download_replaces_a_bad_file_too(weights_folder, fake_drive, tiny_file, caplog):
    from taptr.cli.main import main

    weights_folder.mkdir()
    (weights_folder / "tiny.pth").write_bytes(tiny_file[:1000])
    fake_drive(tiny_file)
    with caplog.at_level(logging.WARNING):
        assert main(["download", "tiny-drive"]) == 0
    assert (weights_folder / "tiny.pth").read_bytes() == tiny_file
    assert "moved aside" in caplog.text


def test_a_kept_file_that_does_not_load_says_what_to_delete(weights_folder, fake_drive, tiny_file):
    weights_folder.mkdir()
    corrupt = tiny_file[:-200] + bytes(200)  # whole size, broken inside: read to be found
    (weights_folder / "tiny.pth").write_bytes(corrupt)
    with pytest.raises(ValueError) as raised:
        taptr.from_pretrained("tiny-drive")
    assert f"delete {weights_folder / 'tiny.pth'}" in str(raised.value) or (
        f"{weights_folder / 'tiny.pth'} is taptr's copy of tiny-drive: delete it"
        in str(raised.value)
    )


# -- trickling, oversized ------------------------------------------------------------------


def test_a_trickling_drive_is_stopped_by_the_least_rate(
    weights_folder, fake_drive, tiny_file, monkeypatch
):
    monkeypatch.setenv("TAPTR_DOWNLOAD_TIMEOUT", QUICK)
    fake = fake_drive(tiny_file, trickle=0.01, trickle_for=8.0)
    error, seconds = _timed(lambda: taptr.from_pretrained("tiny-drive"))
    assert isinstance(error, FileNotFoundError), error
    message = str(error)
    assert "slower than 16,777,216 bytes a second" in message
    assert "TAPTR_DOWNLOAD_MIN_RATE" in message and "nothing was kept" in message
    assert seconds < 5.0 and files_in(weights_folder) == []
    assert fake.sent < len(tiny_file)


def test_a_declared_size_far_above_the_release_is_refused_before_it_is_written(
    weights_folder, fake_drive, tiny_file
):
    fake = fake_drive(tiny_file, padding=64 * 1024**2)  # declares 64 MiB more
    error, seconds = _timed(lambda: taptr.from_pretrained("tiny-drive"))
    assert isinstance(error, FileNotFoundError), error
    declared = len(tiny_file) + 64 * 1024**2
    assert f"the server declares {declared:,} bytes" in str(error)
    assert "nothing was kept" in str(error)
    assert (
        fake.sent < 24 * 1024**2 and files_in(weights_folder) == []
    )  # loopback buffers, not 64 MiB
    assert seconds < 5.0


def test_a_stream_far_above_the_release_is_cut_at_the_bound(weights_folder, fake_drive, tiny_file):
    fake = fake_drive(tiny_file, padding=64 * 1024**2, announce=False)
    error, _ = _timed(lambda: taptr.from_pretrained("tiny-drive"))
    assert isinstance(error, FileNotFoundError), error
    most = release_bytes("tiny")[1]
    assert "the server sent" in str(error) and f"more than the {most:,}" in str(error)
    assert fake.sent < most + 24 * 1024**2 and files_in(weights_folder) == []


def test_the_bounds_are_read_from_the_environment(monkeypatch):
    from taptr.weights import transfer

    monkeypatch.setenv("TAPTR_DOWNLOAD_MIN_RATE", "64K")
    assert transfer.least_rate() == 65536
    monkeypatch.setenv("TAPTR_DOWNLOAD_MIN_RATE", "0")
    assert transfer.least_rate() == 0
    monkeypatch.setenv("TAPTR_DOWNLOAD_MIN_RATE", "fast")
    with pytest.raises(ValueError, match="TAPTR_DOWNLOAD_MIN_RATE='fast' is not a rate"):
        transfer.least_rate()
    monkeypatch.setenv("TAPTR_DOWNLOAD_TIMEOUT", "-1")
    with pytest.raises(ValueError, match="TAPTR_DOWNLOAD_TIMEOUT='-1' is not a number"):
        transfer.answer_seconds(5.0)


# -- offline: fast, and said whole ---------------------------------------------------------


@pytest.fixture
def slow_resolver(monkeypatch):
    """Names ending ``slow.invalid`` fail after `HANG` s (a resolver timing out), other
    ``.invalid`` names at once."""
    real = socket.getaddrinfo
    released = threading.Event()

    def getaddrinfo(host, *args, **kwargs):
        if isinstance(host, str) and host.endswith("slow.invalid"):
            released.wait(HANG)
            raise socket.gaierror(socket.EAI_AGAIN, "Temporary failure in name resolution")
        if isinstance(host, str) and host.endswith(".invalid"):
            raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")
        return real(host, *args, **kwargs)

    monkeypatch.setattr(socket, "getaddrinfo", getaddrinfo)
    yield
    released.set()


def test_a_name_that_resolves_slowly_fails_within_the_timeout(
    weights_folder, slow_resolver, monkeypatch, caplog
):
    monkeypatch.setenv("TAPTR_DOWNLOAD_TIMEOUT", QUICK)
    monkeypatch.setenv("TAPTR_DRIVE_URL", "http://drive.slow.invalid")
    with caplog.at_level(logging.WARNING):
        error, seconds = _timed(lambda: taptr.from_pretrained("taptrv3-official"))
    assert isinstance(error, FileNotFoundError), error
    assert "drive.slow.invalid:80 did not answer within 0.5 s: offline?" in str(error)
    assert seconds < HANG / 2
    assert "downloading" not in caplog.text  # the licence line waits for Drive's answer


def test_offline_the_message_is_whole_and_no_download_is_announced(
    weights_folder, slow_resolver, monkeypatch, caplog
):
    monkeypatch.setenv("TAPTR_DRIVE_URL", "https://drive.google.invalid")
    with caplog.at_level(logging.WARNING):
        error, seconds = _timed(lambda: taptr.from_pretrained("taptrv3-official"))
    message = str(error)
    assert "Drive could not be reached: the name drive.google.invalid does not resolve" in message
    assert "NameResolutionError" not in message and seconds < HANG / 2
    assert "downloading" not in caplog.text


def test_library_errors_are_shortened_at_a_word():
    from taptr.weights.transfer import short_reason

    nested = "HTTPSConnectionPool(host='drive.google.com', port=443): " + "x" * 300
    shortened = short_reason(Exception(nested))
    assert shortened.endswith(" ...") and len(shortened) < 200
    assert shortened.startswith("HTTPSConnectionPool(host='drive.google.com', port=443)")


def test_weights_dir_naming_a_file_says_so(monkeypatch, tmp_path):
    a_file = tmp_path / "weights.txt"
    a_file.write_text("not a folder")
    monkeypatch.setenv("TAPTR_WEIGHTS_DIR", str(a_file))
    with pytest.raises(NotADirectoryError, match=r"TAPTR_WEIGHTS_DIR=.*weights.txt is no folder"):
        taptr.from_pretrained("taptrv3-official")
    monkeypatch.setenv("TAPTR_WEIGHTS_DIR", str(a_file / "inside"))
    with pytest.raises(NotADirectoryError, match="is a file"):
        taptr.from_pretrained("taptrv3-official")


def test_taptr_download_says_weights_dir_names_a_file(monkeypatch, tmp_path, capsys):
    from taptr.cli.main import main

    a_file = tmp_path / "weights.txt"
    a_file.write_text("not a folder")
    monkeypatch.setenv("TAPTR_WEIGHTS_DIR", str(a_file))
    monkeypatch.setenv("TAPTR_OFFLINE", "1")
    assert main(["download", "taptrv3-official"]) == 2
    err = capsys.readouterr().err
    assert "is no folder" in err and "Errno" not in err
