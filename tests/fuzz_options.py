"""Fuzz categories of issue 37: taptr's own files and options.

The file of measured speed choices (any bytes, any JSON, taptr's format with any values),
a result folder's ``settings.json`` (any content, or a folder or a dangling link in its
place), and the options of ``taptr bench``. `tests.fuzz_targets` adds them to its
`CATEGORIES`.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hypothesis import strategies as st

from tests.fuzz_hostile import SilentError

_JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=12,
)


@st.composite
def measured_files(draw: st.DrawFn) -> bytes:
    """Bytes of a measurements file: taptr's format with any values, any JSON, any bytes."""
    from taptr.runtime.measured_file import FORMAT

    shape = draw(st.sampled_from(["taptr", "json", "bytes", "nested"]))
    if shape == "taptr":
        choices = {"k": draw(_JSON), **draw(st.dictionaries(st.text(max_size=8), _JSON))}
        return json.dumps({"format": FORMAT, "choices": choices}).encode()
    if shape == "json":
        return json.dumps(draw(_JSON)).encode()
    if shape == "nested":
        depth = draw(st.integers(1, 100_000))
        return b'{"k":' * depth + b"1" + b"}" * depth
    return draw(st.binary(max_size=256))


def read_measured(data: bytes) -> None:
    """A choice read from ``data``: a valid value, and a foreign file left unchanged."""
    from taptr.runtime.measured import remembered
    from taptr.runtime.measured_file import read_choices

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "measured.json"
        path.write_bytes(data)
        ours = read_choices(path).ours
        value = remembered("k", lambda: 2, path, valid=lambda v: type(v) is int and v in (1, 2))
        if value not in (1, 2) or type(value) is not int:
            raise SilentError(f"invalid choice {value!r}")
        if not ours and path.read_bytes() != data:
            raise SilentError("a file that is not taptr's was replaced")


@st.composite
def settings_entries(draw: st.DrawFn) -> tuple[str, bytes]:
    """What stands where a result folder's ``settings.json`` belongs, and its bytes."""
    kind = draw(st.sampled_from(["file", "folder", "dangling link"]))
    if draw(st.booleans()):
        return kind, json.dumps(draw(_JSON)).encode()
    return kind, draw(st.binary(max_size=128)) + b"[" * draw(st.integers(0, 50_000))


def rerun_over_settings(entry: tuple[str, bytes]) -> None:
    """``made_with`` answers; a rerun either refuses up front or leaves one run's files."""
    from taptr.cli.common.result_settings import SETTINGS_NAME, made_with
    from taptr.io.atomic import result_folder

    kind, data = entry
    owned = ("tracks.csv", SETTINGS_NAME)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        (out / "tracks.csv").write_text("old")
        settings = out / SETTINGS_NAME
        if kind == "file":
            settings.write_bytes(data)
        elif kind == "folder":
            settings.mkdir()
        else:
            settings.symlink_to(out / "missing")
        if made_with(out, {"format": 1}) not in (False, True):
            raise SilentError("made_with gave no answer")
        try:
            with result_folder(out, owned) as staging:
                (staging / "tracks.csv").write_text("new")
                (staging / SETTINGS_NAME).write_text("{}")
        except ValueError:
            if (out / "tracks.csv").read_text() != "old":
                raise SilentError("refused, but the earlier files changed") from None
            raise
        if (out / "tracks.csv").read_text() != "new" or settings.read_text() != "{}":
            raise SilentError("the folder mixes two runs")


@st.composite
def bench_options(draw: st.DrawFn) -> list[str]:
    """A ``taptr bench`` command line, its numbers from sane to absurd."""
    numbers = st.integers(-3, 10) | st.integers(-(2**40), 2**40)
    argv = ["bench", "--preset", draw(st.sampled_from(["tiny", "tiny-v3", "small", "nope"]))]
    for flag in ("--frames", "--threads"):
        if draw(st.booleans()):
            argv += [flag, str(draw(numbers))]
    argv += ["--points", *map(str, draw(st.lists(numbers, min_size=1, max_size=2)))]
    if draw(st.booleans()):
        argv += ["--size", str(draw(numbers)), str(draw(numbers))]
    if draw(st.booleans()):
        argv += ["--history-frames", str(draw(numbers))]
    argv += ["--dtype", draw(st.sampled_from(["float32", "float16"]))]
    return argv


def check_bench(argv: list[str]) -> None:
    """Checks a bench command line up front; no worker may start."""
    from taptr.cli import bench

    parser = argparse.ArgumentParser()
    bench.add_parser(parser.add_subparsers())
    args = parser.parse_args(argv)
    bench.check_bench_arguments(args)  # raises ValueError for what cannot run


CATEGORIES: dict[str, tuple[Any, Callable[[Any], Any]]] = {
    "measured speed choices file": (measured_files(), read_measured),
    "result folder settings.json on rerun": (settings_entries(), rerun_over_settings),
    "taptr bench options": (bench_options(), check_bench),
}
"""The categories of this module, added to `tests.fuzz_targets.CATEGORIES`."""
