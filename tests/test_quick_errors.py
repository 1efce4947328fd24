"""Mistakes that need no model fail at once: before torch is imported, and leave nothing.

Importing torch alone takes seconds and most of a gigabyte, so a misspelled path or a wrong
option value must be reported before it. Each case runs in one fresh interpreter, which
then says whether torch was imported.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from taptr.io.video import write_video

RUNNER = """
import json, sys
import taptr.cli.common.options
from taptr.cli.main import main

taptr.cli.common.options._gpu_device_files = lambda: False  # as on a machine without a GPU
codes, torch_after = [], []
for argv in json.loads(sys.argv[1]):
    codes.append(main(argv))
    torch_after.append("torch" in sys.modules)
print(json.dumps({"codes": codes, "torch": torch_after}))
"""


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("quick")
    frames = np.full((6, 32, 48, 3), 90, np.uint8)
    mask = np.zeros((32, 48), np.uint8)
    mask[8:20, 10:30] = 255
    cv2.imwrite(str(folder / "mask.png"), mask)
    cv2.imwrite(str(folder / "logo.png"), np.zeros((4, 4, 3), np.uint8))
    (folder / "data").mkdir()
    return {"clip": str(write_video(folder / "clip.mp4", frames, fps=6)), "tmp": str(folder)}


CASES = [
    (["track", "{tmp}/missing.mp4", "--grid", "4"], r"video not found: .*missing\.mp4"),
    (["track", "{clip}", "{tmp}/typo.mp4", "--grid", "2"], r"video not found: .*typo\.mp4"),
    (["track", "{clip}", "--grid", "0"], r"--grid must be at least 1"),
    (["track", "{clip}", "--points", "0,999,5"], r"--points: query positions outside"),
    (["track", "{clip}", "--points", "0 1 2"], r"separated by spaces"),
    (["track", "{clip}", "--grid", "2", "--checkpoint", "nope.pth"], r"nope\.pth: file not"),
    (["track", "{clip}", "--grid", "2", "--device", "cdua"], r"--device cdua: not a device"),
    (["track", "{clip}", "--grid", "2", "--device", "cuda"], r"--device cuda: .*no usable CUDA"),
    (["track", "{clip}", "--mask", "{tmp}/none.png", "--device", "cpu"], r"--mask .*not found"),
    (["track", "{clip}", "--grid", "2", "--input-size", "9", "9"], r"--input-size 9 9"),
    (["edit", "{tmp}/missing.mp4", "--mask", "m.png", "--overlay", "o.png"], r"video not found"),
    (
        ["edit", "{clip}", "--mask", "{tmp}/mask.png", "--overlay", "{tmp}/logo.png"]
        + ["--opacity", "2"],
        r"--opacity must lie in \[0, 1\]",
    ),
    (["analyze", "attention", "{tmp}/missing.mp4", "--out", "{tmp}/an"], r"video not found"),
    (
        ["calibrate", "--dataset", "kubric", "--root", "{tmp}/no", "--out", "{tmp}/m.pth"],
        r"--root .*no: not found",
    ),
    (["eval", "--dataset", "davis", "--root", "{tmp}/no", "--out", "{tmp}/ev"], r"--root"),
    (["bench", "--points", "0"], r"--points must be at least 1"),
    (["export", "--format", "onnx", "--out", "{tmp}/x", "--check-frames", "0"], r"--check-fr"),
    (["convert", "{tmp}/nope.pth", "{tmp}/out.pth"], r"checkpoint not found"),
    (["train", "--config", "{tmp}/nope.toml"], r"config file not found"),
    (
        ["train", "preset=small", "data.root={tmp}/data", "out_dir={tmp}/run"],
        r"data\.val_root data/synthetic/val: dataset folder not found.*data\.val_root=",
    ),
]


def test_mistakes_are_reported_before_torch_is_imported(files, tmp_path):
    argvs = [[part.format(**files) for part in argv] for argv, _ in CASES]
    done = subprocess.run(
        [sys.executable, "-c", RUNNER, json.dumps(argvs)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    report = json.loads(done.stdout.strip().splitlines()[-1])
    errors = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(errors) == len(CASES), done.stderr
    for (argv, message), code, line in zip(CASES, report["codes"], errors, strict=True):
        assert code == 2 and re.search(message, line), (argv, line)
    heavy = [argv for (argv, _), torch in zip(CASES, report["torch"], strict=True) if torch]
    assert not heavy, f"torch was imported before the error of {heavy[0]}"
    created = [name for name in ("run", "an", "ev", "x") if Path(files["tmp"], name).exists()]
    assert not created and not list(tmp_path.iterdir()), "a failed command left files"


def test_demo_refuses_port_zero_before_loading(capsys):
    pytest.importorskip("gradio")
    from taptr.cli.main import main

    # Gradio accepted port 0, then failed to reach itself: "ConnectError ... a bug in taptr"
    assert main(["demo", "--port", "0", "--checkpoint", "tiny"]) == 2
    assert "--port must lie in [1, 65535], got 0" in capsys.readouterr().err


def test_install_lines_name_the_extras_packages():
    """A missing optional package is named with a pip line that works from a checkout too."""
    from taptr.messages import install_line

    line = install_line("export")
    assert line.startswith("pip install ") and "taptr[" not in line
    assert "onnxruntime" in line or line == "pip install -e '.[export]'"
    assert install_line("no-such-extra") == "pip install -e '.[no-such-extra]'"
    sources = Path(__file__).resolve().parents[1] / "src" / "taptr"
    quoted = [p for p in sources.rglob("*.py") if "pip install 'taptr[" in p.read_text()]
    assert not quoted, f"install lines that fail from a checkout: {quoted}"
