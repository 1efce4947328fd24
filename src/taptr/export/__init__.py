"""Shipping models outside PyTorch: ONNX and TorchScript graphs of the per-window step.

- `export_model(model, directory, "onnx" | "torchscript")` writes three graphs and a
  manifest (`taptr.export.graphs`);
- `track_points(steps, manifest, frames, ...)` tracks with them through the model's own
  sliding-window driver (`taptr.export.graph_runner`, whose `GraphBackend` adapts the graphs to
  `taptr.model.sliding_window`), with `load_steps(directory)` for the graphs, and `track_video`
  the same in input pixels with (t, x, y) queries (`taptr.export.track_video`);
- `compare(model, directory)` checks an export against the model (`taptr.export.verify`);
- `compile_model(model)` is the optional ``torch.compile`` path for PyTorch inference.

Names are imported on first use, so that importing the package loads neither the
exporters nor onnxruntime.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "export_model": "taptr.export.graphs",
    "ExportManifest": "taptr.export.manifest",
    "track_points": "taptr.export.graph_runner",
    "TrackArrays": "taptr.export.graph_runner",
    "GraphBackend": "taptr.export.graph_runner",
    "track_video": "taptr.export.track_video",
    "load_steps": "taptr.export.backends",
    "OnnxSteps": "taptr.export.backends",
    "TorchScriptSteps": "taptr.export.backends",
    "compare": "taptr.export.verify",
    "compile_model": "taptr.export.compile",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'taptr.export' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)
