"""Running exported graphs: onnxruntime sessions or TorchScript modules behind one interface.

Both classes implement `taptr.export.graph_runner.Steps` (numpy in, numpy out), which
`taptr.export.graph_runner.GraphNetwork` puts under the model's own window driver, whichever the
format. `load_steps` picks the class from the manifest.
"""

from __future__ import annotations

import os
import warnings
from typing import Any

import numpy as np

from taptr.export.manifest import GRAPHS, INPUT_NAMES, ExportManifest
from taptr.onnx.export_files import require_regular
from taptr.onnx.ort_engine import onnxruntime_module, open_sessions


class _GraphSteps:
    """`taptr.export.graph_runner.Steps` over three named graphs; subclasses say how one runs."""

    format: str

    def _load_manifest(self, directory: str | os.PathLike[str]) -> ExportManifest:
        manifest = ExportManifest.load(directory)
        if manifest.format != self.format:
            raise ValueError(f"{directory} holds a {manifest.format} export, not {self.format}")
        return manifest

    def _run(self, name: str, *inputs: np.ndarray) -> list[Any]:
        """Runs graph ``name`` on numpy inputs; its outputs as numpy arrays."""
        raise NotImplementedError

    def encode(self, frames: np.ndarray) -> np.ndarray:
        """Frames (F, 3, H, W) RGB in [0, 1] → memory (F, S, C)."""
        return self._run("encoder", np.ascontiguousarray(frames, np.float32))[0]

    def init_points(self, memory: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """Memory (S, C) of one frame, normalised positions (N, 2) → content (N, C)."""
        return self._run("init_points", memory, positions)[0]

    def decode(self, *inputs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One window; inputs and outputs as `taptr.export.graph_runner.Steps.decode`."""
        positions, visibility, content = self._run("decode_window", *inputs)
        return positions, visibility, content


class OnnxSteps(_GraphSteps):
    """The graphs of an ONNX export, run by onnxruntime.

    Args:
        directory: the export folder.
        threads: intra-op threads per session (default: onnxruntime's, one per core).
        providers: onnxruntime execution providers (default: the CPU provider).
    """

    format = "onnx"

    def __init__(
        self,
        directory: str | os.PathLike[str],
        *,
        threads: int | None = None,
        providers: list[str] | None = None,
    ) -> None:
        onnxruntime_module()  # its message before the manifest's
        self.manifest = self._load_manifest(directory)
        graphs = {name: str(_graph_file(self.manifest, directory, name)) for name in GRAPHS}
        self.sessions = open_sessions(graphs, threads, providers)

    def _run(self, name: str, *inputs: np.ndarray) -> list[Any]:
        feed = dict(zip(INPUT_NAMES[name], inputs, strict=True))
        return self.sessions[name].run(None, feed)


class TorchScriptSteps(_GraphSteps):
    """The graphs of a TorchScript export, run by ``torch.jit`` on the CPU.

    Args:
        directory: the export folder.
    """

    format = "torchscript"

    def __init__(self, directory: str | os.PathLike[str]) -> None:
        import torch

        self.torch = torch
        self.manifest = self._load_manifest(directory)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)  # TorchScript is deprecated upstream
            self.modules = {
                name: torch.jit.load(
                    str(_graph_file(self.manifest, directory, name)), map_location="cpu"
                )
                for name in GRAPHS
            }

    def _run(self, name: str, *inputs: np.ndarray) -> list[np.ndarray]:
        torch = self.torch
        with torch.no_grad():
            outputs = self.modules[name](*(torch.from_numpy(np.asarray(x)) for x in inputs))
        if isinstance(outputs, torch.Tensor):
            outputs = (outputs,)
        return [o.numpy() for o in outputs]


def _graph_file(manifest: ExportManifest, directory: str | os.PathLike[str], name: str) -> str:
    """Graph ``name``'s file, checked to be a regular file before anything opens it."""
    return str(require_regular(manifest.graph_path(directory, name), f"graph {name}"))


def load_steps(
    directory: str | os.PathLike[str], *, threads: int | None = None
) -> OnnxSteps | TorchScriptSteps:
    """The runner for an export folder, by its manifest's format.

    Args:
        directory: the export folder.
        threads: onnxruntime's intra-op threads (TorchScript follows torch's setting).
    """
    manifest = ExportManifest.load(directory)
    if manifest.format == "onnx":
        return OnnxSteps(directory, threads=threads)
    return TorchScriptSteps(directory)
