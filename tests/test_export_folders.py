"""Issue 51: an export folder is shared, copied and edited by hand; nothing in it is trusted.

One regression test per finding: the manifest checked whole against its version, each
error one line naming ``taptr-export.json`` and the key; a manifest read bounded; sizes
bounded before anything is allocated; the ONNX path's memory estimated and refused up
front; ``taptr export`` writing every file through the atomic writer, never through a link;
graphs that are not regular files, or not the graph named, refused by name before an
engine opens them (a FIFO never blocks); ``visibility_threshold=0.0`` not read as "unset";
zero queries and frames that are not an array said plainly; external data outside the
folder refused by the engines. The export used is the small one `tests.fuzz_export` makes
without torch (its graphs open in milliseconds); the memory test measures the tiny model's.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
from importlib.util import find_spec
from pathlib import Path

import numpy as np
import pytest

from taptr.memory_estimate import MemoryEstimateError
from taptr.onnx.graph_engines import open_graphs
from taptr.onnx.manifest_schema import ManifestError
from taptr.onnx.stream_tracker import OnnxOnlineTracker
from taptr.onnx.v3_manifest import V3Manifest
from taptr.onnx.video_tracker import OnnxTracker
from tests.export_v3_cases import EagerGraphs, randomised_v3, tiny_export
from tests.fuzz_export import manifest_fields, write_export
from tests.fuzz_hostile import _within

pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

ENGINES = [
    "onnxruntime",
    pytest.param(
        "openvino",
        marks=pytest.mark.skipif(
            find_spec("openvino") is None,
            reason="openvino is not installed: pip install 'taptr[openvino]'",
        ),
    ),
]


def _edited(edit) -> dict:
    fields = manifest_fields()
    edit(fields)
    return fields


def _set(path: str, value):
    def edit(fields: dict) -> None:
        *parents, last = path.split(".")
        for key in parents:
            fields = fields[key]
        fields[last] = value

    return edit


def _drop(path: str):
    def edit(fields: dict) -> None:
        *parents, last = path.split(".")
        for key in parents:
            fields = fields[key]
        del fields[last]

    return edit


PROBES = {
    "missing support": (_drop("support"), "'support' is missing"),
    "missing a support key": (_drop("support.grid_positions"), "'support.grid_positions' is"),
    "an extra key": (_set("colour", "red"), "'colour' is not a key"),
    "a string for a number": (_set("d_model", "32"), "'d_model' must be a whole number"),
    "a float for a number": (_set("d_model", 32.5), "'d_model' must be a whole number"),
    "a negative size": (_set("input_size", [-48, 64]), "'input_size[0]' must lie in"),
    "a huge size": (_set("d_model", 10**9), "'d_model' must lie in [4, 4,096]"),
    "a boolean for a number": (_set("history_frames", True), "'history_frames' must be"),
    "a history of one": (_set("history_frames", 1), "'history_frames' must be 0"),
    "NaN": (_set("position_eps", float("nan")), "'position_eps' must be a finite number"),
    "an unknown scheme": (_set("support.scheme", "rings"), "'support.scheme' must be one of"),
    "10**6 local offsets": (
        _set("support.local_offsets", [[0.0, 0.0]] * 10**6),
        "larger than the 256 KiB this file may hold",
    ),
    "5,000 local offsets": (
        _set("support.local_offsets", [[0.0, 0.0]] * 5000),
        "'support.local_offsets' must hold at most 4,096 entries",
    ),
    "a list for an object": (_set("support", [1, 2]), "'support' must be an object"),
    "a graph's tensors": (
        _set("graphs.decode_step.inputs", []),
        "'graphs.decode_step.inputs' does not describe",
    ),
    "a file name outside": (_set("files.encoder", "../x.onnx"), "'files.encoder' must be one of"),
    "grid frames for fewer points": (
        _set("support.grid_start_frames", [0]),
        "'support.grid_start_frames' must hold one frame per grid point",
    ),
    "another format version": (_set("taptr_export", 7), "'taptr_export' is 7"),
}


@pytest.mark.parametrize("name", sorted(PROBES))
def test_manifest_is_checked_whole_against_its_version(name, tmp_path):
    edit, message = PROBES[name]
    folder = write_export(tmp_path, _edited(edit))
    with pytest.raises(ManifestError) as refused:
        V3Manifest.load(folder)
    text = str(refused.value)
    assert "taptr-export.json" in text and message in text and "\n" not in text


@pytest.mark.parametrize(
    ("raw", "message"),
    [
        (b"\xff\xfe{}", "not UTF-8 text"),
        (b'{"taptr_export": 1,', "not JSON"),
        (b"[" * 100_000 + b"]" * 100_000, "nested too deeply"),
        (b'{"a": ' * 50 + b"1" + b"}" * 50, "nested more than 8 levels"),
        (b"[1, 2]", "must hold a JSON object"),
    ],
)
def test_manifest_bytes_are_refused_in_one_line(raw, message, tmp_path):
    with pytest.raises(ManifestError, match=message) as refused:
        V3Manifest.load(write_export(tmp_path, raw))
    assert "taptr-export.json" in str(refused.value)


def test_a_1_gb_manifest_is_not_read_whole(tmp_path):
    path = tmp_path / "taptr-export.json"
    with open(path, "wb") as stream:
        stream.truncate(2**30)  # sparse: a gigabyte of zeros on no disk
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(ManifestError, match="larger than the 256 KiB"):
        V3Manifest.load(tmp_path)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 64 * 1024  # KiB


def test_the_v2_manifest_is_checked_too(tmp_path):
    from taptr.export.manifest import ExportManifest

    fields = {"taptr_export": 1, "format": "onnx", "input_size": [64, 64], "d_model": 32}
    (tmp_path / "taptr-export.json").write_text(json.dumps(fields))
    with pytest.raises(ManifestError, match="'spatial_shapes' is missing"):
        ExportManifest.load(tmp_path)


# -- memory ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def model():
    return randomised_v3()


def test_100000_queries_are_refused_before_the_run(model, monkeypatch):
    monkeypatch.setenv("TAPTR_MAX_MEMORY", "64G")  # any machine: far below 3 TB
    tracker = OnnxTracker(graphs=EagerGraphs(model))
    video = np.zeros((4, 48, 64, 3), np.uint8)
    queries = np.zeros((100_000, 3), np.float32)
    with pytest.raises(MemoryEstimateError, match="tracking 100,036 points") as refused:
        tracker.track(video, queries)
    assert "track fewer points" in str(refused.value)
    online = OnnxOnlineTracker(tracker)
    stream = online.start(frame_size=(48, 64))
    with pytest.raises(MemoryEstimateError):
        online.add_queries(stream, queries)
    assert len(stream.loop.start_frames) == 0  # nothing was added


PEAK = """
import json, sys
with open("/proc/self/clear_refs", "w") as stream:
    stream.write("5")  # the peak starts here: a forked child's would include its parent's
import numpy as np
from taptr.onnx import OnnxTracker
from taptr.onnx.graph_memory import estimate_run
tracker = OnnxTracker(sys.argv[1], threads=1, support_points="none")
queries = np.c_[np.zeros(1500), np.full(1500, 20.0), np.full(1500, 30.0)].astype(np.float32)
tracker.track(np.zeros((3, 48, 64, 3), np.uint8), queries)
with open("/proc/self/status") as stream:
    peak = next(int(line.split()[1]) * 1024 for line in stream if line.startswith("VmHWM"))
estimate = estimate_run(tracker.manifest, 1500, 3, None, tracker.graph_bytes).total
print(json.dumps({"peak": peak, "estimate": estimate}))
"""


@pytest.mark.skipif(not os.path.exists("/proc/self/clear_refs"), reason="needs Linux's peak reset")
def test_the_estimate_holds_a_measured_run(tmp_path_factory):
    graphs = tiny_export(tmp_path_factory.getbasetemp()) / "graphs"
    run = subprocess.run(
        [sys.executable, "-c", PEAK, str(graphs)], capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 0, run.stderr[-2000:]
    measured = json.loads(run.stdout.splitlines()[-1])
    assert measured["peak"] <= measured["estimate"] <= 4 * measured["peak"]


# -- writing -------------------------------------------------------------------------------------


def _fake_onnx_export(module, inputs, path, names, dynamic_shapes) -> None:
    Path(path).write_bytes(b"graph")  # the exporter's part, without its minute


def test_taptr_export_never_writes_through_a_link(model, tmp_path, monkeypatch, capsys):
    from taptr.cli.main import main
    from taptr.weights.checkpoint import save_checkpoint

    monkeypatch.setattr("taptr.export.v3_graphs.export_onnx_graph", _fake_onnx_export)
    checkpoint = save_checkpoint(model, tmp_path / "v3.pth")
    out, outside = tmp_path / "out", tmp_path / "outside"
    out.mkdir(), outside.mkdir()
    for name in ("encoder.onnx", "decode_step.onnx", "taptr-export.json"):
        (outside / name).write_text("not yours")
        (out / name).symlink_to(outside / name)
    assert (
        main(["export", "--format", "onnx", "--out", str(out), "--checkpoint", str(checkpoint)])
        == 0
    )
    for name in ("encoder.onnx", "decode_step.onnx", "taptr-export.json"):
        assert (outside / name).read_text() == "not yours"
        assert (out / name).is_file() and not (out / name).is_symlink()
    assert (out / "encoder.onnx").read_bytes() == b"graph"
    assert sorted(p.name for p in out.iterdir()) == [
        "decode_step.onnx",
        "encoder.onnx",
        "start_points.onnx",
        "taptr-export.json",
    ]  # no temporary left behind


def test_torchscript_export_never_writes_through_a_link(tmp_path):
    import taptr
    from taptr.export.graphs import export_model

    out, outside = tmp_path / "out", tmp_path / "outside.pt"
    out.mkdir()
    outside.write_text("not yours")
    (out / "encoder.pt").symlink_to(outside)
    export_model(taptr.build_model("tiny").eval(), out, "torchscript")
    assert outside.read_text() == "not yours" and not (out / "encoder.pt").is_symlink()


# -- graphs ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("engine", ENGINES)
def test_a_fifo_graph_is_refused_without_blocking(engine, tmp_path):
    folder = write_export(tmp_path / "export")
    (folder / "encoder.onnx").unlink()
    os.mkfifo(folder / "encoder.onnx")
    with pytest.raises(ValueError, match=r"graph encoder .*encoder.onnx is a FIFO"):
        _within(lambda: open_graphs(folder, engine), [folder / "encoder.onnx"])


@pytest.mark.parametrize("engine", ENGINES)
def test_graphs_that_are_folders_or_other_graphs_are_named(engine, tmp_path):
    folder = write_export(tmp_path / "export")
    (folder / "start_points.onnx").unlink()
    (folder / "start_points.onnx").mkdir()
    with pytest.raises(ValueError, match=r"start_points\.onnx is a folder, not a regular file"):
        open_graphs(folder, engine)
    (folder / "start_points.onnx").rmdir()
    (folder / "start_points.onnx").write_bytes((folder / "encoder.onnx").read_bytes())
    with pytest.raises(ValueError, match="is not the start_points graph the manifest describes"):
        open_graphs(folder, engine)


def _external_graph(folder: Path, location: str) -> None:
    """``encoder.onnx`` whose weight lies in external data at ``location``."""
    import onnx
    from onnx import TensorProto, helper

    weight = helper.make_tensor("w", TensorProto.FLOAT, [1], [0.0])
    weight.ClearField("float_data")
    weight.data_location = TensorProto.EXTERNAL
    for key, value in (("location", location), ("length", "4")):
        entry = weight.external_data.add()
        entry.key, entry.value = key, value
    frames = helper.make_tensor_value_info("frames", TensorProto.FLOAT, None)
    memory = helper.make_tensor_value_info("memory", TensorProto.FLOAT, None)
    node = helper.make_node("Add", ["frames", "w"], ["memory"])
    graph = helper.make_graph([node], "encoder", [frames], [memory], [weight])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 9
    onnx.save(model, str(folder / "encoder.onnx"))


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("where", ["../outside.bin", "absolute", "link.bin", "/etc/passwd"])
def test_external_data_outside_the_folder_is_refused(engine, where, tmp_path):
    folder = write_export(tmp_path / "export")
    outside = tmp_path / "outside.bin"
    outside.write_bytes(np.zeros(1, np.float32).tobytes())
    (folder / "link.bin").symlink_to(outside)
    _external_graph(folder, str(outside) if where == "absolute" else where)
    with pytest.raises(ValueError, match=r"encoder\.onnx: (onnxruntime|OpenVINO) cannot"):
        open_graphs(folder, engine)


# -- what users pass -----------------------------------------------------------------------


def test_a_threshold_of_zero_is_not_read_as_unset(model):
    with pytest.raises(ValueError, match=r"visibility_threshold must lie in \(0, 1\), got 0.0"):
        OnnxTracker(graphs=EagerGraphs(model), visibility_threshold=0.0)
    assert (
        OnnxTracker(graphs=EagerGraphs(model), visibility_threshold=0.3).visibility_threshold == 0.3
    )


def test_zero_queries_and_frames_that_are_not_an_array(model):
    tracker = OnnxTracker(graphs=EagerGraphs(model))
    video = np.zeros((3, 48, 64, 3), np.uint8)
    for queries in (np.zeros((0, 3)), []):
        result = tracker.track(video, queries, backward=True)
        assert result.tracks.shape == (3, 0, 2) and result.visibility.shape == (3, 0)
    online = OnnxOnlineTracker(tracker)
    stream = online.start(frame_size=(48, 64))
    assert online.add_queries(stream, []) == []
    assert online.step(stream, video).tracks.shape == (2, 0, 2)
    with pytest.raises(ValueError, match=r"frames must be a uint8 numpy array .* got list"):
        online.step(stream, video[0].tolist())
