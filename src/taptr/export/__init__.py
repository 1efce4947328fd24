"""Shipping models outside PyTorch: graphs of each model's step, built and checked.

This room holds what needs torch: building the graphs, writing their manifest, checking
them against the model. Running a TAPTRv3 export needs no torch and lives in
`taptr.onnx` (its trackers are named here too, imported from there on first use).

- `export_model(model, directory, "onnx" | "torchscript")` writes three graphs and a
  manifest (`taptr.export.graphs`); for TAPTRv3, three ONNX graphs of its per-frame step
  with every state explicit (`taptr.export.v3_graphs`);
- `OnnxTracker(directory)` and `OnnxOnlineTracker` are `taptr.onnx`'s: whole videos and
  streams over a TAPTRv3 export in numpy, with onnxruntime or OpenVINO, without torch;
- `track_points(steps, manifest, frames, ...)` tracks with them through the model's own
  sliding-window driver (`taptr.export.graph_runner`, whose `GraphNetwork` adapts the graphs to
  `taptr.model.sliding_window`), with `load_steps(directory)` for the graphs, and `track_video`
  the same in input pixels with (t, x, y) queries (`taptr.export.track_video`);
- `compare(model, directory)` checks an export against the model (`taptr.export.verify`).

Names are imported on first use, so that importing the package loads neither the
exporters nor an engine; no module here imports onnxruntime or OpenVINO at import
(tests/test_rooms.py).
"""

from __future__ import annotations

from taptr.lazy import lazy_names

_EXPORTS = {
    "export_model": "taptr.export.graphs",
    "ExportManifest": "taptr.export.manifest",
    "track_points": "taptr.export.graph_runner",
    "TrackArrays": "taptr.task.results",
    "GraphNetwork": "taptr.export.graph_runner",
    "track_video": "taptr.export.track_video",
    "load_steps": "taptr.export.graph_steps",
    "OnnxSteps": "taptr.export.graph_steps",
    "TorchScriptSteps": "taptr.export.graph_steps",
    "compare": "taptr.export.verify",
    "export_v3": "taptr.export.v3_graphs",
}

_RUNNERS = {
    "V3Manifest": "taptr.onnx.v3_manifest",
    "OnnxTracker": "taptr.onnx.video_tracker",
    "OnnxOnlineTracker": "taptr.onnx.stream_tracker",
}
"""`taptr.onnx`'s names, importable from here as before (documented there)."""

__all__ = sorted(_EXPORTS)


__getattr__ = lazy_names(__name__, {**_EXPORTS, **_RUNNERS})
