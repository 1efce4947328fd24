"""The web demo end to end: ``taptr demo`` on 127.0.0.1 driven by Debian's headless Chromium.

Starts the real command in a subprocess (the untrained tiny model, so it is fast), uploads a
generated clip, clicks two points, runs the tracking, and checks that the overlay video plays
and that ``tracks.csv`` has T × 2 rows. A screenshot is saved as ``demo.png`` under the test's
temporary folder. The server's temporary folder, working folder and home must be left empty.

Needs /usr/bin/chromium (``apt-get install chromium``) and the ``playwright`` package; the
browser is never downloaded (no ``playwright install``).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from taptr.data.sample_video import make_sample_clip
from taptr.io.tracks import CSV_HEADER
from taptr.io.video import write_video

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
NUM_FRAMES, HEIGHT, WIDTH = 12, 96, 128
STARTUP_TIMEOUT_S = 90.0
UI_TIMEOUT_MS = 60_000

if not CHROMIUM.exists():
    pytest.skip(
        "Debian's Chromium is not installed (apt-get install chromium)", allow_module_level=True
    )
sync_api = pytest.importorskip(
    "playwright.sync_api", reason="playwright is not installed (pip install playwright)"
)


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _wait_until_serving(server: subprocess.Popen, url: str, log: Path) -> None:
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while time.monotonic() < deadline:
        if server.poll() is not None:
            pytest.fail(f"taptr demo exited with {server.returncode}:\n{log.read_text()}")
        try:
            with urllib.request.urlopen(url, timeout=2):
                return
        except OSError:
            time.sleep(0.5)
    pytest.fail(f"taptr demo did not answer within {STARTUP_TIMEOUT_S} s:\n{log.read_text()}")


@pytest.fixture
def server(tmp_path):
    """``taptr demo`` on a free loopback port, with its own temp, working and home folders."""
    folders = {name: tmp_path / name for name in ("server-tmp", "server-cwd", "server-home")}
    for folder in folders.values():
        folder.mkdir()
    env = {
        **os.environ,
        "TMPDIR": str(folders["server-tmp"]),
        "HOME": str(folders["server-home"]),
        "OMP_NUM_THREADS": "1",  # a shared 2-core machine
        # Importing torchvision makes torch create its (empty) compile cache under TMPDIR;
        # it is torch's, not the demo's, so it goes elsewhere and TMPDIR is checked strictly.
        "TORCHINDUCTOR_CACHE_DIR": str(tmp_path / "torch-cache"),
    }
    port = _free_port()
    log = tmp_path / "server.log"
    command = [sys.executable, "-m", "taptr.cli.main", "demo", "--checkpoint", "tiny"]
    with open(log, "w") as out:
        process = subprocess.Popen(
            [*command, "--device", "cpu", "--port", str(port)],
            cwd=folders["server-cwd"],
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    url = f"http://127.0.0.1:{port}/"
    try:
        _wait_until_serving(process, url, log)
        yield url
    finally:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    assert process.returncode == 0, log.read_text()
    assert "Keyboard interruption" not in log.read_text()  # SIGTERM stops it quietly
    for name, folder in folders.items():
        left = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*"))
        assert not left, f"the demo left files in its {name} folder: {left[:10]}"


def test_upload_click_track_download(server, tmp_path):
    started = time.monotonic()
    clip = make_sample_clip(num_frames=NUM_FRAMES, height=HEIGHT, width=WIDTH)
    video_path = write_video(tmp_path / "sample.mp4", clip.video, clip.fps)
    screenshot = tmp_path / "demo.png"
    browser_home = tmp_path / "browser-home"
    with sync_api.sync_playwright() as playwright:
        context = playwright.chromium.launch_persistent_context(
            str(tmp_path / "chromium-profile"),  # a new, empty profile
            executable_path=str(CHROMIUM),
            args=CHROMIUM_ARGS,
            headless=True,
            viewport={"width": 1280, "height": 1100},
            # Chromium writes crash-report settings under $HOME even with its own profile.
            env={**os.environ, "HOME": str(browser_home)},
        )
        context.set_default_timeout(UI_TIMEOUT_MS)
        try:
            page = context.new_page()
            page.goto(server)
            page.locator("#video-input input[type=file]").set_input_files(str(video_path))
            frame = page.locator("#query-frame img")
            frame.wait_for()
            assert frame.evaluate("img => [img.naturalWidth, img.naturalHeight]") == [WIDTH, HEIGHT]
            box = frame.bounding_box()
            assert box is not None
            clicks = [(0.25, 0.5), (0.75, 0.25)]  # fractions of the shown frame
            for count, (fx, fy) in enumerate(clicks, start=1):
                frame.click(position={"x": fx * box["width"], "y": fy * box["height"]})
                page.wait_for_function(
                    "n => document.querySelector('#points textarea').value"
                    ".split('\\n').filter(Boolean).length === n",
                    arg=count,
                )
            page.click("#track")
            page.wait_for_function(
                "() => { const v = document.querySelector('#overlay-video video');"
                " return v !== null && v.readyState >= 1 && v.videoWidth > 0; }"
            )
            size = page.locator("#overlay-video video").evaluate(
                "v => [v.videoWidth, v.videoHeight]"
            )
            link = page.locator("#tracks-csv a").first
            link.wait_for()
            href = link.get_attribute("href")
            assert href is not None and href.startswith(server)
            csv = page.request.get(href).text()
            page.screenshot(path=str(screenshot), full_page=True)
        finally:
            context.close()
    assert size == [WIDTH, HEIGHT]
    lines = csv.strip().splitlines()
    assert lines[0] == CSV_HEADER
    assert len(lines) - 1 == NUM_FRAMES * 2
    # On the query frame each point is where it was clicked (pixel centres at integers).
    rows = [[float(v) for v in line.split(",")] for line in lines[1:3]]
    for (fx, fy), (frame_index, _, x, y, visible) in zip(clicks, rows, strict=True):
        assert frame_index == 0 and visible == 1
        assert abs(x - (fx * WIDTH - 0.5)) <= 1 and abs(y - (fy * HEIGHT - 0.5)) <= 1
    assert screenshot.stat().st_size > 0
    print(f"\nscreenshot: {screenshot}; browser part {time.monotonic() - started:.1f} s")
