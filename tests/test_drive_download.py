"""TAPTRv3's weights from Google Drive, end to end, against a fake Drive on 127.0.0.1.

The fake (`tests.fake_drive`) answers as Drive does for a large file: a confirmation page
first, the file at the address its form makes. ``TAPTR_DRIVE_URL`` (the testing hook of
`taptr.weights.drive_download`) points taptr at it. Nothing leaves the machine. Hostile
servers (trickling, oversized, late) are in tests/test_download_bounds.py.
"""

from __future__ import annotations

import logging
import socket
import sys
import time

import pytest

import taptr
from taptr.model.v3 import TAPTRv3
from taptr.weights import drive_download, registry
from taptr.weights.checkpoint import CheckpointError
from tests.fake_drive import R18_ID, R50_ID, files_in

pytest.importorskip("gdown")


def test_taptrv3_downloads_once_through_the_confirmation_page(
    weights_folder, fake_drive, official_v3_checkpoint, caplog
):
    fake = fake_drive(official_v3_checkpoint.read_bytes())
    weights_folder.mkdir()  # what a download killed outright (SIGKILL) left: removed by the next
    (weights_folder / ".TAPTRv3_resnet18_384x512.999999999-dead.tmp.pth").write_bytes(b"half")
    with caplog.at_level(logging.WARNING):
        predictor = taptr.Predictor.from_pretrained("taptrv3-official", device="cpu")
    assert isinstance(predictor.model, TAPTRv3) and predictor.input_size == (384, 512)
    assert fake.requests == ["/uc", "/download"]  # the page first, then its form's address
    assert "IDEA License 1.0, non-commercial" in caplog.text  # said before the download
    assert files_in(weights_folder) == ["TAPTRv3_resnet18_384x512.pth"]  # no temporaries left
    assert (weights_folder / "TAPTRv3_resnet18_384x512.pth").read_bytes() == fake.content
    # once: the folder answers from now on, without a request
    assert (
        registry.manual_path("taptrv3-official") == weights_folder / "TAPTRv3_resnet18_384x512.pth"
    )
    assert len(fake.requests) == 2


def test_a_file_served_without_confirmation_is_taken_as_it_comes(
    weights_folder, fake_drive, official_v3_checkpoint
):
    fake = fake_drive(official_v3_checkpoint.read_bytes(), direct=True)
    assert registry.download("taptrv3-official").read_bytes() == fake.content
    assert fake.requests == ["/uc", "/uc"]  # asked once, then fetched by gdown


def test_an_interrupted_download_leaves_nothing_that_looks_complete(
    weights_folder, fake_drive, official_v3_checkpoint
):
    content = official_v3_checkpoint.read_bytes()
    fake_drive(content, cut_at=len(content) // 2)
    with pytest.raises(FileNotFoundError) as raised:
        taptr.from_pretrained("taptrv3-official")
    message = str(raised.value)
    assert "the download broke off" in message and R18_ID in message
    assert "\n" not in message
    assert files_in(weights_folder) == []  # neither the file nor gdown's partial one


def test_a_file_cut_short_is_refused_by_its_size(
    weights_folder, fake_drive, official_v3_checkpoint
):
    fake_drive(official_v3_checkpoint.read_bytes()[: 1 << 20])  # announced and sent: 1 MiB
    with pytest.raises(CheckpointError, match=r"1,048,576 bytes, but its weights take at least"):
        taptr.from_pretrained("taptrv3-official")
    assert files_in(weights_folder) == []


def test_a_drive_page_instead_of_the_file_is_refused(weights_folder, fake_drive):
    page = b"<!DOCTYPE html><html><body>Too many users have viewed or downloaded this file"
    fake_drive(page + b" " * 100, kind="text/html")
    with pytest.raises(CheckpointError, match=r"is a web page \(HTML\), not weights"):
        taptr.from_pretrained("taptrv3-official")
    assert files_in(weights_folder) == []


def test_drives_download_limit_is_said_with_the_link(weights_folder, fake_drive):
    fake = fake_drive(b"unused", quota=True)
    with pytest.raises(FileNotFoundError) as raised:
        taptr.from_pretrained("taptrv3-official")
    message = str(raised.value)
    assert "Drive did not give the file (" in message and "Too many users" in message
    assert R18_ID in message and "\n" not in message
    assert fake.requests == ["/uc"] and files_in(weights_folder) == []


def test_another_models_weights_are_refused_with_what_they_are(
    weights_folder, fake_drive, official_checkpoint, official_v3_checkpoint
):
    fake_drive(official_checkpoint.read_bytes())  # TAPTRv2 under TAPTRv3's name
    with pytest.raises(CheckpointError) as raised:
        taptr.from_pretrained("taptrv3-official")
    message = str(raised.value)
    assert "holds TAPTRv2 (ResNet-50 backbone, C = 256)" in message
    assert "taptrv3-official is TAPTRv3 (ResNet-18 backbone, C = 256)" in message
    # issue 45: the refused download was never kept, so there is nothing to delete
    assert "nothing was kept" in message and "delete" not in message
    fake_drive(official_v3_checkpoint.read_bytes())  # ResNet-18 under the ResNet-50 name
    with pytest.raises(CheckpointError, match=r"holds TAPTRv3 \(ResNet-18.*is TAPTRv3 \(ResNet-50"):
        taptr.from_pretrained("taptrv3-r50-official")
    assert files_in(weights_folder) == []


def test_without_gdown_or_offline_the_message_of_today_stays(
    weights_folder, fake_drive, monkeypatch, caplog
):
    fake = fake_drive(b"unused")
    monkeypatch.setitem(sys.modules, "gdown", None)
    with pytest.raises(FileNotFoundError) as raised, caplog.at_level(logging.WARNING):
        taptr.from_pretrained("taptrv3-official")
    assert "downloading" not in caplog.text  # no licence notice for a download never tried
    message = str(raised.value)
    assert "gdown is not installed (pip install 'gdown" in message
    assert f"https://drive.google.com/file/d/{R18_ID}" in message and "in a browser" in message
    monkeypatch.delitem(sys.modules, "gdown")
    monkeypatch.setenv("TAPTR_OFFLINE", "1")
    with pytest.raises(FileNotFoundError, match="downloads are disabled"):
        taptr.from_pretrained("taptrv3-official")
    assert fake.requests == []


def test_unreachable_drive_is_said_at_once(weights_folder, monkeypatch):
    with socket.socket() as probe:  # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    monkeypatch.setenv("TAPTR_DRIVE_URL", f"http://127.0.0.1:{port}")
    started = time.perf_counter()
    with pytest.raises(FileNotFoundError, match="Drive could not be reached"):
        taptr.from_pretrained("taptrv3-official")
    assert time.perf_counter() - started < drive_download.PROBE_TIMEOUT


def test_taptr_download_fetches_ahead_of_time(
    weights_folder, fake_drive, official_v3_checkpoint, capsys
):
    from taptr.cli.main import main

    fake = fake_drive(official_v3_checkpoint.read_bytes())
    assert main(["download", "taptrv3-official"]) == 0
    path = weights_folder / "TAPTRv3_resnet18_384x512.pth"
    assert path.read_bytes() == fake.content
    assert str(path) in capsys.readouterr().out
    assert main(["download", "taptrv3-official"]) == 0  # already there: no second transfer
    assert fake.requests.count("/download") == 1


def test_drive_links_give_their_file_ids():
    assert drive_download.file_id(registry.MANUAL["taptrv3-official"].url) == R18_ID
    assert drive_download.file_id(registry.MANUAL["taptrv3-r50-official"].url) == R50_ID
    assert (
        drive_download.file_id("https://drive.google.com/uc?export=download&id=abc-_1") == "abc-_1"
    )
    with pytest.raises(ValueError, match="not a Google Drive file link"):
        drive_download.file_id("https://example.com/weights.pth")
