"""What the TAPTRv3 export tests share: seeded models, eager graphs, one export per run."""

from __future__ import annotations

import contextlib
import io
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from filelock import FileLock

import taptr
from taptr.cli.main import main
from taptr.export.v3_graphs import prepare_v3, v3_manifest, v3_wrappers
from taptr.model.v3.taptr import TAPTRv3
from taptr.weights.checkpoint import save_checkpoint


def randomised_v3(preset: str = "tiny-v3", seed: int = 0, **changes) -> TAPTRv3:
    """A seeded TAPTRv3 whose zero-initialised parameters (position heads) are non-zero."""
    config = taptr.get_config(preset).replace(**changes)
    torch.manual_seed(seed)
    model = taptr.build_model(config).eval()
    with torch.no_grad():
        for param in model.parameters():
            if not param.any():
                param.normal_(0, 0.1)
    assert isinstance(model, TAPTRv3)
    return model


class EagerGraphs:
    """`taptr.onnx.graph_engines.StepGraphs` over the PyTorch wrappers, before any export."""

    def __init__(
        self,
        model: TAPTRv3,
        input_size: tuple[int, int] | None = None,
        history_frames: int | None = None,
    ) -> None:
        prepared = prepare_v3(model)
        self.manifest = v3_manifest(prepared, input_size, history_frames)
        self.modules = v3_wrappers(prepared, self.manifest)

    def _run(self, name: str, *inputs: np.ndarray) -> list[np.ndarray]:
        with torch.no_grad():
            outputs = self.modules[name](*(torch.from_numpy(np.asarray(x)) for x in inputs))
        if isinstance(outputs, torch.Tensor):
            outputs = (outputs,)
        return [o.numpy() for o in outputs]

    def encode(self, frames: np.ndarray) -> np.ndarray:
        return self._run("encoder", frames)[0]

    def start_points(self, memory, positions):
        outputs = self._run("start_points", memory, positions)
        return outputs[0], (outputs[1] if len(outputs) > 1 else None)

    def decode_step(self, inputs):
        names = self.manifest.input_names("decode_step")
        return tuple(self._run("decode_step", *(inputs[name] for name in names)))


def exported_once(base_temp: Path, name: str, export: Callable[[Path], object]) -> Path:
    """A folder ``export`` wrote once per test run, shared by pytest-xdist's workers.

    ``base_temp``: pytest's base temporary folder (its workers' have a common parent).
    The first test to ask exports under a lock; the others wait and read its folder.
    """
    root = base_temp.parent if os.environ.get("PYTEST_XDIST_WORKER") else base_temp
    folder = root / name
    with FileLock(str(folder) + ".lock"):
        done = folder / "done"
        if not done.is_file():
            export(folder)
            done.write_text(str(os.getpid()))
    return folder


HISTORY = 6
"""The shared tiny export's history limit (``--history-frames``): 100 frames run its FIFO."""


def tiny_export(base_temp: Path) -> Path:
    """The tiny TAPTRv3 (`randomised_v3`) exported once per run by ``taptr export --check``.

    The folder holds ``graphs/`` (the export), ``tiny_v3.pth`` (the model) and
    ``printed.txt`` (what the command printed).
    """

    def export(folder: Path) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        checkpoint = save_checkpoint(randomised_v3(), folder / "tiny_v3.pth")
        printed = io.StringIO()
        command = ["export", "--format", "onnx", "--out", str(folder / "graphs")]
        command += ["--checkpoint", str(checkpoint), "--history-frames", str(HISTORY)]
        command += ["--check", "--check-frames", "9", "--check-points", "5", "--threads", "1"]
        with contextlib.redirect_stdout(printed):
            assert main(command) == 0
        (folder / "printed.txt").write_text(printed.getvalue())

    return exported_once(base_temp, "tiny_v3_onnx", export)
