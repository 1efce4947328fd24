"""Shipping models outside PyTorch: graphs of each model's step, and loops that drive them.

- `export_model(model, directory, "onnx" | "torchscript")` writes three graphs and a
  manifest (`taptr.export.graphs`); for TAPTRv3, three ONNX graphs of its per-frame step
  with every state explicit (`taptr.export.v3_graphs`);
- `OnnxTracker(directory)` tracks whole videos with a TAPTRv3 export in numpy and
  onnxruntime, without torch (`taptr.export.v3_tracker`), and `OnnxOnlineTracker` streams
  frame by frame with points added and removed at any time (`taptr.export.v3_online`);
- `track_points(steps, manifest, frames, ...)` tracks with them through the model's own
  sliding-window driver (`taptr.export.graph_runner`, whose `GraphBackend` adapts the graphs to
  `taptr.model.sliding_window`), with `load_steps(directory)` for the graphs, and `track_video`
  the same in input pixels with (t, x, y) queries (`taptr.export.track_video`);
- `compare(model, directory)` checks an export against the model (`taptr.export.verify`).

Names are imported on first use, so that importing the package loads neither the
exporters nor onnxruntime.
"""

from __future__ import annotations

from taptr.lazy import lazy_names

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
    "export_v3": "taptr.export.v3_graphs",
    "V3Manifest": "taptr.export.v3_manifest",
    "OnnxGraphs": "taptr.export.v3_sessions",
    "OnnxTracker": "taptr.export.v3_tracker",
    "OnnxOnlineTracker": "taptr.export.v3_online",
}

__all__ = sorted(_EXPORTS)


__getattr__ = lazy_names(__name__, _EXPORTS)
