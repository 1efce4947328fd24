"""TAPTRv3's exported graphs run without torch: the frame loop, its trackers and engines.

What the tracker does (queries, support points, both-ways fusion, resizing) is
`taptr.task`'s; this room runs it over the three ONNX graphs `taptr export` writes, with
numpy and an engine chosen by name:

- `OnnxTracker` tracks whole videos (`taptr.onnx.video_tracker`), `OnnxOnlineTracker`
  streams frame by frame with points added and removed at any time
  (`taptr.onnx.stream_tracker`);
- `open_graphs(directory, engine)` opens the graphs in ``onnxruntime`` (presets ``cpu``,
  ``cuda``, ``cuda-graphs``, ``tensorrt``; `taptr.onnx.ort_engine`) or ``openvino``
  (`taptr.onnx.openvino_engine`), behind one protocol (`taptr.onnx.graph_engines`);
- `V3Manifest` reads and checks the export's ``taptr-export.json``
  (`taptr.onnx.v3_manifest`), the contract of the loop (`taptr.onnx.frame_loop`,
  `taptr.onnx.ring_history`).

Nothing here imports torch (tests/test_rooms.py checks every module in a process where
torch cannot be imported). Names are imported on first use, so that importing the package
loads no engine.
"""

from __future__ import annotations

from taptr.lazy import lazy_names

_EXPORTS = {
    "OnnxTracker": "taptr.onnx.video_tracker",
    "TrackResult": "taptr.onnx.video_tracker",
    "OnnxOnlineTracker": "taptr.onnx.stream_tracker",
    "OnnxStream": "taptr.onnx.stream_tracker",
    "open_graphs": "taptr.onnx.graph_engines",
    "ENGINES": "taptr.onnx.graph_engines",
    "StepGraphs": "taptr.onnx.graph_engines",
    "OnnxRuntimeGraphs": "taptr.onnx.ort_engine",
    "OpenVinoGraphs": "taptr.onnx.openvino_engine",
    "V3Manifest": "taptr.onnx.v3_manifest",
    "ManifestError": "taptr.onnx.manifest_schema",
}

__all__ = sorted(_EXPORTS)


__getattr__ = lazy_names(__name__, _EXPORTS)
