"""TAPTRv3's exported graphs run by onnxruntime, numpy in and out, without torch.

`OnnxGraphs` opens the three graphs of a TAPTRv3 export (`taptr.export.v3_manifest`) as
onnxruntime sessions and implements `taptr.export.v3_loop.V3Graphs` for the loop.
Denormal floats are flushed to zero, as the PyTorch predictor does on a CPU
(`taptr.runtime.denormals`): products of small weights and activations otherwise take a
path tens of times slower on x86 CPUs.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from taptr.export.sessions import onnxruntime_module, open_sessions
from taptr.export.v3_manifest import GRAPHS, V3Manifest


class OnnxGraphs:
    """The graphs of a TAPTRv3 export as onnxruntime sessions.

    Args:
        directory: the export folder.
        threads: intra-op threads per session (default: onnxruntime's, one per core).
        providers: onnxruntime execution providers, in order of preference (default: the
            CPU's), as names or (name, options) pairs.

    Raises:
        ModuleNotFoundError: onnxruntime is missing.
        ValueError: the folder holds another model's export.
    """

    def __init__(
        self,
        directory: str | os.PathLike[str],
        *,
        threads: int | None = None,
        providers: list[Any] | None = None,
    ) -> None:
        onnxruntime_module()  # its message before the manifest's
        self.manifest = V3Manifest.load(directory)
        graphs = {name: str(self.manifest.graph_path(directory, name)) for name in GRAPHS}
        self.sessions = open_sessions(graphs, threads, providers)

    def encode(self, frames: np.ndarray) -> np.ndarray:
        """Frames (F, 3, H, W) RGB in [0, 1] → memory (F, S, C)."""
        feed = {"frames": np.ascontiguousarray(frames, np.float32)}
        return self.sessions["encoder"].run(None, feed)[0]

    def start_points(
        self, memory: np.ndarray, positions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Memory (S, C), positions (N, 2) → content (N, C), context (N, K, K, C) or None."""
        feed = {"memory": memory, "positions": np.ascontiguousarray(positions, np.float32)}
        outputs = self.sessions["start_points"].run(None, feed)
        return outputs[0], (outputs[1] if len(outputs) > 1 else None)

    def decode_step(self, inputs: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
        """``decode_step``'s named inputs → new positions (N, 4), visibility (N, 3), features."""
        return tuple(self.sessions["decode_step"].run(None, inputs))
