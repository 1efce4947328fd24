"""Shipping models outside PyTorch: ONNX and TorchScript graphs of the per-window step.

- `export_model(model, directory, "onnx" | "torchscript")` writes three graphs and a
  manifest (`taptr.export.graphs`);
- `track_points(steps, manifest, frames, ...)` is the reference sliding-window loop over
  them, in numpy (`taptr.export.runner`), with `load_steps(directory)` for the graphs, and
  `track_video` the same in input pixels with (t, x, y) queries (`taptr.export.video`);
- `compare(model, directory)` checks an export against the model (`taptr.export.verify`);
- `compile_model(model)` is the optional ``torch.compile`` path for PyTorch inference.

Names are imported on first use, so that the runner works without torch.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "export_model": "taptr.export.graphs",
    "ExportManifest": "taptr.export.manifest",
    "track_points": "taptr.export.runner",
    "TrackArrays": "taptr.export.runner",
    "track_video": "taptr.export.video",
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
