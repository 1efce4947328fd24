"""What the TAPTRv3 export tests share: seeded models, eager graphs, one export per run."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from filelock import FileLock

import taptr
from taptr.export.v3_graphs import prepare_v3, v3_manifest, v3_wrappers
from taptr.model.v3.taptr import TAPTRv3


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
    """`taptr.export.v3_loop.V3Graphs` over the PyTorch wrappers, before any export."""

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


def exported_once(
    tmp_path_factory, worker_id: str, name: str, export: Callable[[Path], object]
) -> Path:
    """A folder ``export`` wrote once per test run, shared by pytest-xdist's workers.

    The first worker to ask exports under a lock; the others wait and read its folder.
    """
    if worker_id == "master":
        folder = tmp_path_factory.mktemp(name)
        export(folder)
        return folder
    root = tmp_path_factory.getbasetemp().parent
    folder = root / name
    with FileLock(str(folder) + ".lock"):
        done = folder / "done"
        if not done.is_file():
            export(folder)
            done.write_text(str(os.getpid()))
    return folder
