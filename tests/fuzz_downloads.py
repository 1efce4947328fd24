"""Fuzz categories of issue 45: kept capture timings, and downloads from a misbehaving Drive.

`tests.fuzz_targets` adds them to its `CATEGORIES`. Each target has an oracle beyond "a
clean error or a valid result":

- kept capture timings: any value kept under a capture key (numbers of any size or sign,
  NaN, text, missing or extra keys) is read without an error; a timing read must lie
  within physical bounds, and a six-frame run captures only when that timing pays.
- downloads: the fake Drive of `tests.fake_drive` answers late, trickles, declares or
  streams far more than the file, serves a web page or its quota page, cuts the transfer,
  or serves the file over a bad one already at the target. The download must end within
  `DOWNLOAD_SECONDS`, leave at the target either the file or nothing (a bad file moved
  aside, no temporaries), and stop an oversized response near its bound.
"""

from __future__ import annotations

import contextlib
import functools
import io
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch
from hypothesis import strategies as st

from tests.fuzz_hostile import SilentError, _env

DOWNLOAD_SECONDS = 12.0
"""Longest a fuzzed download may take, its bounds set to 0.3 s and 16 MiB/s (most take a
fraction of a second; the slack is for a loaded machine)."""

SLACK_BYTES = 16 * 1024**2
"""Bytes past the size bound the server may have sent to a refused transfer: what loopback's
socket buffers take in before the client reads (several MiB), and a chunk of gdown's."""

PADDING = 64 * 1024**2
"""What an oversized response adds: far beyond the bound and the slack, so that writing it
all shows."""

# -- kept capture timings ------------------------------------------------------------------

_SECONDS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(10**500), 10**500),
    st.sampled_from([10**400, -(10**400), 1e308, 5e-324, 0, 0.0, 1, 3600, 3601, True, None]),
    st.text(max_size=4),
)


@st.composite
def kept_timings(draw: st.DrawFn) -> Any:
    """A value kept under a capture key: a timing of any numbers, or something else."""
    if draw(st.integers(0, 9)) == 0:
        return draw(st.one_of(st.none(), st.lists(_SECONDS, max_size=3), _SECONDS))
    timing = {key: draw(_SECONDS) for key in ("eager_s", "captured_s", "capture_s")}
    if draw(st.integers(0, 5)) == 0:
        timing.pop(draw(st.sampled_from(sorted(timing))))
    if draw(st.integers(0, 5)) == 0:
        timing["extra"] = 1.0
    return timing


def run_over_kept_timing(value: Any) -> None:
    """Reads a kept timing and runs six frames over it with a stand-in captured step."""
    from taptr.runtime import capture_timing, step_capture
    from taptr.runtime.measured import keep

    timing = capture_timing.CaptureTiming.read(value)
    if timing is not None:
        _check_bounds(timing)
    ran: list[str] = []
    with tempfile.TemporaryDirectory() as folder, _env(TAPTR_MEASURED=f"{folder}/m.json"):
        keep("key", value)
        with _stand_in(step_capture, ran):
            step = step_capture.StepCapture(
                lambda *args: ran.append("eager") or args[0],
                torch.device("cpu"),
                "auto",
                lambda points: "key",
                5,
                6,
                clock=lambda: 0.0,
            )
            for _ in range(6):
                step(torch.zeros(1, 1, 5, 4))
    should = timing is not None and timing.pays(6)
    if ("captured" in ran) != should:
        raise SilentError(f"six frames {'captured' if not should else 'eager'} over {value!r}")


def _check_bounds(timing: Any) -> None:
    from taptr.runtime.capture_timing import MAX_CAPTURE_SECONDS, MAX_STEP_SECONDS

    steps = [timing.eager_s] + ([timing.captured_s] if timing.captured_s != float("inf") else [])
    if not all(0 < s <= MAX_STEP_SECONDS for s in steps):
        raise SilentError(f"a step time out of bounds was trusted: {timing}")
    if not 0 <= timing.capture_s <= MAX_CAPTURE_SECONDS:
        raise SilentError(f"a capture cost out of bounds was trusted: {timing}")


@contextlib.contextmanager
def _stand_in(module: Any, ran: list[str]) -> Iterator[None]:
    """Replaces the compiled step by a stand-in that records its calls."""
    real = module.captured_step

    def captured(*args: Any) -> Any:
        ran.append("captured")
        return args[0]

    module.captured_step = lambda decoder, device: captured
    try:
        yield
    finally:
        module.captured_step = real


# -- downloads from a misbehaving Drive ----------------------------------------------------

BEHAVIOURS = (
    "valid",
    "late",
    "trickle",
    "declared oversize",
    "streamed oversize",
    "web page",
    "quota page",
    "cut short",
    "partial file at the target",
    "web page at the target",
)

downloads = st.tuples(st.sampled_from(BEHAVIOURS), st.integers(0, 2**20))
"""(how the fake Drive misbehaves, a size or offset it uses)."""

_FILE_ID = "fuzz-drive-id"


@functools.cache
def _tiny_file() -> bytes:
    from taptr import build_model
    from taptr.weights.checkpoint import checkpoint_dict

    torch.manual_seed(0)
    stream = io.BytesIO()
    torch.save(checkpoint_dict(build_model("tiny")), stream)
    return stream.getvalue()


def _server_options(behaviour: str, number: int, content: bytes) -> dict[str, Any]:
    """The fake Drive's options for ``behaviour``; ``number`` sizes or places its lie."""
    big = PADDING + number
    return {
        "valid": {},
        "late": {"late": 2.0},
        "trickle": {"trickle": 0.002, "trickle_for": 2 * DOWNLOAD_SECONDS},
        "declared oversize": {"padding": big},
        "streamed oversize": {"padding": big, "announce": False},
        "web page": {"kind": "text/html"},
        "quota page": {"quota": True},
        "cut short": {"cut_at": number % len(content)},
        "partial file at the target": {},
        "web page at the target": {},
    }[behaviour]


def download_from_misbehaving_drive(case: tuple[str, int]) -> None:
    """Fetches tiny weights from the fake Drive misbehaving as ``case`` says."""
    behaviour, number = case
    content = _tiny_file()
    if behaviour == "web page":
        content = b"<!DOCTYPE html><html>" + bytes(number % 4096) + b"</html>"
    with tempfile.TemporaryDirectory() as folder, _registered(Path(folder)) as target:
        before = None
        if behaviour.endswith("at the target"):
            target.parent.mkdir(parents=True)
            before = b"<html>quota</html>" if "web page" in behaviour else _tiny_file()[:number]
            target.write_bytes(before)
        options = _server_options(behaviour, number, content)
        _fetch_and_check(content, options, target, before)


def _fetch_and_check(
    content: bytes, options: dict[str, Any], target: Path, before: bytes | None
) -> None:
    from taptr.weights import registry
    from taptr.weights.drive import release_bytes
    from tests.fake_drive import FakeDrive

    fake = FakeDrive(content, ids=(_FILE_ID,), **options)
    started = time.monotonic()
    try:
        with _env(TAPTR_DRIVE_URL=fake.url):
            _outcome(lambda: registry.load_model("fuzz-drive"), target, content, before)
    finally:
        fake.close()
        seconds = time.monotonic() - started
        left = sorted(p.name for p in target.parent.glob("*") if p.name != "tiny.pth.rejected")
        if seconds > DOWNLOAD_SECONDS:
            raise SilentError(f"a download took {seconds:.1f} s")
        if fake.sent > release_bytes("tiny")[1] + SLACK_BYTES:
            raise SilentError(f"{fake.sent:,} bytes were taken from an oversized response")
        if left not in ([], ["tiny.pth"]):
            raise SilentError(f"left in the weights folder: {left}")


def _outcome(load: Callable[[], Any], target: Path, content: bytes, before: bytes | None) -> None:
    """A loaded model is the served file (or a whole one there before), kept at the target;
    an error leaves the target as it was or empty, never with a download in it."""
    try:
        choice = load()
    except (ValueError, FileNotFoundError):
        if target.exists() and target.read_bytes() != before:
            raise SilentError("a refused download left a file at the target") from None
        raise
    if choice.model.config.d_model != 32 or target.read_bytes() not in (content, before):
        raise SilentError("the loaded model is not the served file")


@contextlib.contextmanager
def _registered(folder: Path) -> Iterator[Path]:
    """``fuzz-drive`` registered as Drive weights (the tiny preset) fetched into ``folder``."""
    from taptr.weights import registry
    from taptr.weights.drive import ManualWeights

    weights = folder / "weights"
    url = f"https://drive.google.com/file/d/{_FILE_ID}"
    registry.MANUAL["fuzz-drive"] = ManualWeights(url, "tiny.pth", "tiny", "tiny", "")
    bounds = {"TAPTR_DOWNLOAD_TIMEOUT": "0.3", "TAPTR_DOWNLOAD_MIN_RATE": "16M"}
    offline = {key: "0" for key in ("TAPTR_OFFLINE", "HF_HUB_OFFLINE")}
    try:
        with _env(TAPTR_WEIGHTS_DIR=str(weights), **bounds, **offline):
            yield weights / "tiny.pth"
    finally:
        del registry.MANUAL["fuzz-drive"]


CATEGORIES: dict[str, tuple[Any, Callable[[Any], Any]]] = {
    "kept capture timings": (kept_timings(), run_over_kept_timing),
    "downloads from a misbehaving Drive": (downloads, download_from_misbehaving_drive),
}
"""The categories of this module, added to `tests.fuzz_targets.CATEGORIES`."""
