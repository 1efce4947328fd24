"""The worst inputs of the hostile-input reviews (issues 15 and 29), one per run.

``python scripts/bomb_cases.py --list`` names the cases; ``python scripts/bomb_cases.py
NAME`` builds that input in a temporary folder (a few kilobytes to a megabyte, from
`tests.bombs`), runs it through the reader or command a user would, and prints one line
``NAME<TAB>peak RSS in bytes<TAB>outcome``. `scripts/fuzz_report.py` runs every case in a
child of its own under an address-space cap; one case by hand::

    prlimit --as=8589934592 /usr/bin/time -v python scripts/bomb_cases.py "pth: view"
"""

from __future__ import annotations

import os
import pickle
import resource
import sys
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from tests import bombs  # noqa: E402

GIB = bombs.GIB


def _tapvid(path: Path) -> None:
    from taptr.data.tapvid import iter_tapvid

    for pending in iter_tapvid("davis", path):
        pending.load()


def _frames_pickle(path: Path, frame: bytes, count: int) -> Path:
    item = {
        "video": [frame] * count,
        "points": np.full((1, count, 2), 0.5),
        "occluded": np.zeros((1, count), bool),
    }
    path.write_bytes(pickle.dumps({"bomb": item}, protocol=4))
    return path


def _cli(*argv: str) -> None:
    """Runs ``taptr ARGV``; a user error (status 2) becomes the ValueError it printed."""
    import contextlib
    import io

    from taptr.cli.main import main

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        status = main(list(argv))
    lines = [line for line in err.getvalue().splitlines() if "error:" in line]
    if status == 2:
        raise ValueError(lines[-1] if lines else err.getvalue().strip()[-200:])
    if status:
        raise RuntimeError(f"status {status}: {err.getvalue().strip()[-300:]}")


def _findings(root: str) -> None:
    """``taptr check-data ROOT``'s check; its first error becomes a ValueError."""
    from taptr.data.check import check_kubric_folder

    report = check_kubric_folder(root)
    if report.errors:
        raise ValueError(f"check-data: {report.errors[0].message}")


def _clip(folder: Path) -> Path:
    from taptr.io.video import write_video

    frames = np.random.default_rng(0).integers(0, 256, (12, 48, 64, 3), dtype=np.uint8)
    return write_video(folder / "clip.mp4", frames, fps=10)


def _write(path: Path, data: bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


def _kubric_with(folder: Path, frame: bytes) -> Path:
    from taptr.data.kubric import write_sequence
    from taptr.types import TrackingSample

    sample = TrackingSample(
        np.zeros((8, 16, 16, 3), np.uint8), np.ones((8, 2, 2), np.float32), np.ones((8, 2), bool)
    )
    write_sequence(folder / "kubric" / "0000", sample)
    _write(folder / "kubric" / "0000" / "frames" / "001.png", frame)
    return folder / "kubric"


def _config_checkpoint(folder: Path, **config: object) -> Path:
    from taptr.weights.checkpoint import checkpoint_dict
    from taptr.weights.registry import load_model

    data = checkpoint_dict(load_model(None).model)
    data["config"] = dict(data["config"], **config)
    torch.save(data, folder / "big_input.pth")
    return folder / "big_input.pth"


def _cases(folder: Path) -> dict[str, Callable[[], object]]:
    """Every case by name: a call that reads its input."""
    from taptr.api.regions import read_mask
    from taptr.cli.edit import _read_overlay
    from taptr.data.kubric import read_sequence
    from taptr.io.video import read_video
    from taptr.weights.checkpoint import load_checkpoint

    f = folder
    cases: dict[str, Callable[[], object]] = {"baseline": lambda: None}
    for name, data in bombs.pickle_bombs().items():
        path = _write(f / f"{name}.pkl", data)
        cases[f"pickle {name}"] = lambda p=path: _tapvid(p)  # type: ignore[misc]
    cases |= {
        "pickle 20,000 frames": lambda: _tapvid(
            _frames_pickle(f / "a.pkl", bombs.png_bytes(256, 256), 20_000)
        ),
        "pickle PNG frames → 4.6 GB": lambda: _tapvid(
            _frames_pickle(f / "b.pkl", bombs.png_bytes(4096, 4096), 92)
        ),
        "pickle PNG decompression bomb": lambda: _tapvid(
            _frames_pickle(f / "c.pkl", bombs.png_bomb(), 2)
        ),
        "npy header 7.28 TiB": lambda: read_sequence(
            bombs.npy_header_bomb(_kubric_with(f, bombs.png_bytes(16, 16)) / "0000" / "0000.npy")
            .parent
        ),
        "frame folder PNG bomb": lambda: read_video(
            _write(f / "v" / "0.png", bombs.png_bomb()).parent
        ),
        "pth bytearray(12 GiB)": lambda: load_checkpoint(
            bombs.call_checkpoint(f / "a.pth", bytearray, 12 * GIB)
        ),
        "pth FloatTensor(3 Gi)": lambda: load_checkpoint(
            bombs.call_checkpoint(f / "b.pth", torch.FloatTensor, 3 * GIB)
        ),
        "pth zip storage 12 GiB": lambda: load_checkpoint(
            bombs.torch_zip(
                f / "c.pth",
                {"w": bombs.tensor_ref("0", 3 * GIB)},
                {"0": (torch.FloatStorage, 3 * GIB, bytes(12))},
            )
        ),
        "pth legacy storage 12 GiB": lambda: load_checkpoint(
            bombs.legacy_checkpoint(f / "d.pth", 3 * GIB)
        ),
        # issue 29
        "track: 35-byte GIF declaring 16000x16000": lambda: _cli(
            "track", str(_write(f / "bomb.gif", bombs.gif_canvas())), "--grid", "2",
            "--out", str(f / "o"),
        ),
        "read_video: the same GIF": lambda: read_video(_write(f / "g.gif", bombs.gif_canvas())),
        "mask: PNG declaring 25000x25000 16-bit RGBA": lambda: read_mask(
            _write(f / "m.png", bombs.png_bomb(25_000, 25_000, depth=16, colour=6))
        ),
        "edit --overlay: the same PNG": lambda: _read_overlay(
            str(_write(f / "o.png", bombs.png_bomb(25_000, 25_000, depth=16, colour=6)))
        ),
        "frame folder: Radiance HDR named 0.png": lambda: read_video(
            _write(f / "h" / "0.png", bombs.hdr_image(1000, 1000)).parent
        ),
        "check-data: HDR named 001.png": lambda: _findings(
            str(_kubric_with(f, bombs.hdr_image(1000, 1000)))
        ),
        "pth: record deflating to 3 GiB (3 MB file)": lambda: load_checkpoint(
            bombs.deflated_checkpoint(f / "e.pth", 3 * GIB)
        ),
        "pth: view of 1.5e9 floats over 4 bytes (1 MB)": lambda: load_checkpoint(
            bombs.view_checkpoint(f / "v.pth", 1_500_000_000)
        ),
        "pth: config value nested 100,000 deep": lambda: load_checkpoint(
            bombs.deep_config_checkpoint(f / "n.pth")
        ),
        "pth: /dev/zero": lambda: load_checkpoint(Path("/dev/zero")),
        "track --input-size 4096 4096": lambda: _cli(
            "track", str(_clip(f)), "--grid", "2", "--input-size", "4096", "4096",
            "--out", str(f / "o"),
        ),
        "track: checkpoint config asking 4096x4096": lambda: _cli(
            "track", str(_clip(f)), "--grid", "2", "--checkpoint",
            str(_config_checkpoint(f, input_size=[4096, 4096])), "--out", str(f / "o"),
        ),
        "track --grid 316 (99,856 points)": lambda: _cli(
            "track", str(_clip(f)), "--grid", "316", "--out", str(f / "o")
        ),
        "track: FIFO named clip.mp4": lambda: _cli(
            "track", str(_fifo(f / "fifo.mp4")), "--grid", "2", "--out", str(f / "o")
        ),
        "track: video spliced 32x32 then 64x48": lambda: _cli(
            "track", str(bombs.spliced_video(f / "s.mkv")), "--grid", "2", "--out", str(f / "o")
        ),
        "track --points 0,1e39,10": lambda: _cli(
            "track", str(_clip(f)), "--points", "0,1e39,10", "--out", str(f / "o")
        ),
        "track --max-frames 10**20": lambda: _cli(
            "track", str(_clip(f)), "--grid", "2", "--max-frames", str(10**20),
            "--out", str(f / "o"),
        ),
    }  # fmt: skip
    return cases


def _fifo(path: Path) -> Path:
    os.mkfifo(path)
    return path


def run(name: str) -> str:
    """``NAME<TAB>peak RSS<TAB>outcome`` of one case."""
    with tempfile.TemporaryDirectory() as folder:
        cases = _cases(Path(folder))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                cases[name]()
            outcome = "ok" if name == "baseline" else "LOADED"
        except (ValueError, FileNotFoundError) as error:
            outcome = "clean: " + " ".join(str(error).replace(folder, "<tmp>").split())[:150]
        except BaseException as error:
            outcome = f"TRACEBACK {type(error).__name__}: {error}"[:160]
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return f"{name}\t{peak}\t{outcome}"


if __name__ == "__main__":
    os.environ.setdefault("HF_HUB_OFFLINE", "1")  # the bundled model, never the network
    if sys.argv[1:] == ["--list"]:
        with tempfile.TemporaryDirectory() as listing:
            print("\n".join(_cases(Path(listing))))
    else:
        print(run(sys.argv[1]), flush=True)
