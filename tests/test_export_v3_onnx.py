"""TAPTRv3 exported to ONNX (tiny preset): the command, the graphs, the torch-free runner.

One export per test run (``taptr export ... --check``, shared by pytest-xdist's workers
through `tests.export_v3_cases.exported_once`) serves every test here: the graphs at sizes
other than the tracing examples, a 100-frame stream with points added and removed
mid-stream against `OnlineTracker`, whole videos against `Predictor` both ways in time,
and the runner in a process where torch cannot be imported.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from taptr.api.online import OnlineTracker
from taptr.api.predictor import Predictor
from taptr.model.v3.context_attention import ContextAwareDeformableAttention
from taptr.onnx.ort_engine import OnnxRuntimeGraphs as OnnxGraphs
from taptr.onnx.stream_tracker import OnnxOnlineTracker
from taptr.onnx.v3_manifest import V3Manifest
from taptr.onnx.v3_tensors import GRAPHS
from taptr.onnx.video_tracker import OnnxTracker
from tests.export_v3_cases import HISTORY, EagerGraphs, randomised_v3, tiny_export
from tests.test_export_v3_loop import _stream_run

pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")


@pytest.fixture(scope="module")
def model():
    return randomised_v3()


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """The shared export folder (`tests.export_v3_cases.tiny_export`)."""
    return tiny_export(tmp_path_factory.getbasetemp())


def test_command_writes_the_graphs_and_checks_them(exported):
    printed = (exported / "printed.txt").read_text()
    manifest = V3Manifest.load(exported / "graphs")
    assert all(manifest.graph_path(exported / "graphs", name).is_file() for name in GRAPHS)
    assert (manifest.version, manifest.format, manifest.input_size) == (3, "onnx", (48, 64))
    assert (manifest.history_frames, manifest.context_patch, manifest.d_model) == (HISTORY, 3, 32)
    assert manifest.support.scheme == "grid" and len(manifest.support.grid_positions) == 36
    shapes = {s.name: s.shape for s in manifest.graphs["decode_step"]["inputs"]}
    assert shapes["history_content"] == ("points", "slots", 32)
    assert "64×48 frames" in printed and "check on the 9-frame sample clip" in printed
    assert float(printed.split("max |Δ| positions ")[1].split()[0]) <= 1e-4
    assert float(printed.split("visibility logits ")[1].split(";")[0]) <= 1e-4


def test_graphs_hold_at_other_sizes(model, exported):
    """Graph by graph against the eager wrappers, with sizes the tracing never saw."""
    onnx = OnnxGraphs(exported / "graphs", threads=1)
    eager = EagerGraphs(model)
    attention = model.decoder.layers[0].cross_attention
    assert type(attention) is ContextAwareDeformableAttention  # the export works on a copy
    assert model.execution.name == "fast"
    rng = np.random.default_rng(0)
    frames = rng.random((3, 3, 48, 64), dtype=np.float32)
    memory = eager.encode(frames)
    np.testing.assert_allclose(onnx.encode(frames), memory, atol=2e-5, rtol=0)
    np.testing.assert_allclose(onnx.encode(frames[:1]), memory[:1], atol=2e-5, rtol=0)
    for points, slots in ((1, 1), (7, 16), (11, 5)):
        positions = rng.uniform(0, 1, (points, 2)).astype(np.float32)
        content, context = eager.start_points(memory[0], positions)
        got = onnx.start_points(memory[0], positions)
        np.testing.assert_allclose(got[0], content, atol=2e-5, rtol=0)
        np.testing.assert_allclose(got[1], context, atol=2e-5, rtol=0)
        held = rng.random(slots) < 0.7
        held[0] = True
        inputs = {
            "memory": memory[1],
            "frame": np.array(20, np.int64),
            "start_frames": rng.integers(0, 22, points),
            "initial_content": content,
            "context": context,
            "positions": rng.normal(0, 1, (points, 4)).astype(np.float32),
            "visibility": rng.normal(0, 3, (points, 3)).astype(np.float32),
            "history_content": (content[:, None] + rng.normal(0, 0.1, (points, slots, 32))).astype(
                np.float32
            ),
            "history_visibility": rng.normal(0, 2, (points, slots)).astype(np.float32),
            "slot_frames": np.arange(20 - slots + 1, 21, dtype=np.int64)[rng.permutation(slots)],
            "slot_held": held,
        }
        for value, reference in zip(
            onnx.decode_step(inputs), eager.decode_step(inputs), strict=True
        ):
            assert value.shape == reference.shape
            np.testing.assert_allclose(value, reference, atol=5e-5, rtol=0)


def _predictor(model, **options) -> Predictor:
    return Predictor(
        model, device="cpu", capture="off", frames_per_call=1, history_frames=HISTORY, **options
    )


def _plan(height: int, width: int) -> dict[int, list]:
    """Points added and removed over 100 frames (some ahead of their query frame)."""
    rng = np.random.default_rng(7)

    def points(frame: int, count: int) -> np.ndarray:
        xy = rng.uniform(0, [width - 1, height - 1], (count, 2))
        return np.concatenate([np.full((count, 1), frame), xy], 1).astype(np.float32)

    return {
        0: [("add", points(0, 4))],
        10: [("add", points(12, 3))],
        30: [("remove", [1, 5])],
        31: [("add", points(31, 2))],
        55: [("remove", [0]), ("add", points(60, 2))],
        80: [("remove", [2, 7]), ("add", points(80, 1))],
    }


def test_stream_of_100_frames_matches_the_online_tracker(model, exported):
    frames = np.random.default_rng(8).integers(0, 256, (100, 60, 80, 3), np.uint8)  # resized
    plan = _plan(60, 80)
    online = OnlineTracker(_predictor(model))
    expected = _stream_run(online, lambda: online.start(frame_size=(60, 80)), frames, plan)
    onnx = OnnxOnlineTracker(OnnxTracker(exported / "graphs", threads=1))
    got = _stream_run(onnx, lambda: onnx.start(frame_size=(60, 80)), frames, plan)
    assert got[0].keys() == expected[0].keys() and len(got[0]) > 300
    tracks = np.array([got[0][key] - expected[0][key] for key in expected[0]])
    logits = np.array([got[1][key] - expected[1][key] for key in expected[1]])
    assert np.abs(tracks).max() <= 2e-3  # pixels of 60 × 80 frames
    finite = np.isfinite(logits)  # ±inf before and on each query frame, in both
    assert np.abs(logits[finite]).max() <= 1e-3


def test_track_matches_the_predictor_both_ways(model, exported):
    video = np.random.default_rng(9).integers(0, 256, (16, 48, 64, 3), np.uint8)
    queries = np.array([[0, 5.0, 7.0], [6, 33.0, 20.5], [15, 63.0, 47.0]], np.float32)
    expected = _predictor(model).track(video, queries, backward=True)
    got = OnnxTracker(exported / "graphs", threads=1).track(video, queries, backward=True)
    np.testing.assert_allclose(got.tracks, expected.tracks[0].numpy(), atol=2e-3, rtol=0)
    np.testing.assert_allclose(
        got.visibility_logits, expected.visibility_logits[0].numpy(), atol=1e-3, rtol=0
    )


TORCH_FREE = """
import json, sys
sys.modules["torch"] = None  # any import of torch now raises ImportError
import numpy as np
from taptr.export import OnnxOnlineTracker, OnnxTracker
tracker = OnnxTracker(sys.argv[1], threads=1)
video = np.random.default_rng(10).integers(0, 256, (8, 48, 64, 3), np.uint8)
result = tracker.track(video, np.array([[0, 10.0, 12.0], [3, 40.0, 30.0]]), backward=True)
online = OnnxOnlineTracker(tracker)
stream = online.start()
updates = [online.step(stream, video[:4])]
online.add_queries(stream, [[4, 20.0, 20.0]])
updates += [online.step(stream, video[4:]), online.finish(stream)]
loaded = {name.split(".")[0] for name, module in sys.modules.items() if module is not None}
print(json.dumps({
    "tracks": result.tracks.tolist(),
    "streamed": [u.tracks.shape[:2] for u in updates],
    "torch": "torch" in loaded,
}))
"""


def test_runner_needs_no_torch(exported):
    run = subprocess.run(
        [sys.executable, "-c", TORCH_FREE, str(exported / "graphs")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    printed = json.loads(run.stdout.splitlines()[-1])
    assert not printed["torch"]
    assert printed["streamed"] == [[3, 0], [4, 1], [1, 1]]  # frames 0-2, 3-6, 7
    video = np.random.default_rng(10).integers(0, 256, (8, 48, 64, 3), np.uint8)
    tracker = OnnxTracker(exported / "graphs", threads=1)
    result = tracker.track(video, np.array([[0, 10.0, 12.0], [3, 40.0, 30.0]]), backward=True)
    np.testing.assert_array_equal(np.array(printed["tracks"], np.float32), result.tracks)
