"""The torch-free TAPTRv3 loop gives the PyTorch driver's, predictor's and stream's tracks.

The graphs run here as their eager wrappers (no export, `tests.export_v3_cases.EagerGraphs`),
so that every rule of the numpy loop is checked in seconds: starts, skipped frames, the
history and its FIFO limit, start labels, models without contexts, resizing, support
points, the backward pass, the stream's added and removed points.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from taptr.api.online import OnlineTracker
from taptr.api.predictor import Predictor
from taptr.api.resize import resize_frames as torch_resize
from taptr.model.taptr import normalize_frames
from taptr.model.trajectory import QuerySet
from taptr.model.v3.per_frame import run_frames
from taptr.onnx.frame_loop import track_points
from taptr.onnx.ring_history import RingHistory
from taptr.onnx.stream_tracker import FrameCountError, OnnxOnlineTracker
from taptr.onnx.video_tracker import OnnxTracker
from taptr.runtime.frames import EncodedFrames
from taptr.task.resizing import resize_frames
from tests.export_v3_cases import EagerGraphs, randomised_v3


@pytest.fixture(scope="module")
def model():
    return randomised_v3()


def _frames(num_frames: int, size=(48, 64), seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random((num_frames, 3, *size), dtype=np.float32)


def _driver(model, frames, starts, positions, visible=None, history=None):
    """The PyTorch driver's last-layer positions (T, N, 2) and logits (T, N, 3)."""
    video = normalize_frames(torch.from_numpy(frames))[None]
    labels = torch.ones(len(starts), dtype=torch.bool) if visible is None else visible
    queries = QuerySet(
        torch.from_numpy(starts)[None], torch.from_numpy(positions)[None], labels[None]
    )
    with torch.no_grad():
        source = EncodedFrames(model, video)
        out = run_frames(model, queries, len(frames), source, torch.float32, history_frames=history)
    return out.positions[0].numpy(), out.visibility_logits[0].numpy()


@pytest.mark.parametrize(
    ("num_frames", "starts", "history"),
    [
        (12, [0, 3, 3, 7, 11], None),  # points on the first, a shared and the last frame
        (30, [0, 2, 9, 20, 29], 4),  # FIFO: 4 frames held, the buffer overwritten in place
        (25, [10, 14], 0),  # frames 0..10 skipped: no point past its start
    ],
)
def test_loop_matches_the_driver(model, num_frames, starts, history):
    frames = _frames(num_frames)
    starts = np.array(starts, np.int64)
    positions = np.random.default_rng(1).uniform(0.05, 0.95, (len(starts), 2)).astype(np.float32)
    expected = _driver(model, frames, starts, positions, history=history)
    got = track_points(EagerGraphs(model), frames, num_frames, starts, positions, None, history)
    np.testing.assert_allclose(got.positions, expected[0], atol=3e-5, rtol=0)
    np.testing.assert_allclose(got.visibility_logits, expected[1], atol=1e-4, rtol=0)


@pytest.mark.parametrize(
    "changes",
    [
        {"visibility_weights": False},  # unwritten frames carry the start label
        {"context_attention": False},  # no context tensors in the graphs
    ],
)
def test_loop_matches_the_driver_for_ablations(changes):
    model = randomised_v3(**changes)
    frames = _frames(10)
    starts = np.array([0, 2, 5], np.int64)
    positions = np.array([[0.2, 0.3], [0.5, 0.5], [0.9, 0.1]], np.float32)
    visible = torch.tensor([True, False, True])
    expected = _driver(model, frames, starts, positions, visible)
    graphs = EagerGraphs(model)
    assert (graphs.manifest.context_patch == 0) == ("context_attention" in changes)
    got = track_points(graphs, frames, 10, starts, positions, visible.numpy())
    np.testing.assert_allclose(got.positions, expected[0], atol=3e-5, rtol=0)
    np.testing.assert_allclose(got.visibility_logits, expected[1], atol=1e-4, rtol=0)


def test_ring_history_holds_the_last_frames_in_order():
    history = RingHistory(channels=2, limit=5)
    history.add_points(1)
    for frame in range(13):
        history.open_frame(frame, np.full((1, 2), frame, np.float32), np.zeros(1, np.float32))
    assert (history.first, history.length, len(history.slot_held)) == (8, 5, 5)
    held = history.slot_frames[history.slot_held]
    assert sorted(held) == list(range(8, 13))
    assert all(
        history.content[0, slot, 0] == frame for slot, frame in enumerate(history.slot_frames)
    )
    unlimited = RingHistory(channels=2, limit=0)
    unlimited.add_points(2)
    for frame in range(20):
        unlimited.open_frame(frame, np.full((2, 2), frame, np.float32), np.zeros(2, np.float32))
    assert len(unlimited.slot_held) == 32 and unlimited.slot_held.sum() == 20
    with pytest.raises(ValueError, match="in order"):
        unlimited.open_frame(25, np.zeros((2, 2), np.float32), np.zeros(2, np.float32))
    with pytest.raises(ValueError, match="at least 2"):
        RingHistory(channels=2, limit=1)


def test_resize_matches_the_predictor():
    video = np.random.default_rng(0).integers(0, 256, (2, 70, 90, 3), np.uint8)
    chw = torch.from_numpy(video).permute(0, 3, 1, 2)
    for method in ("bilinear", "lanczos"):
        for size in ((48, 64), (96, 128), (70, 90)):
            expected = torch_resize(chw, size, method).numpy()
            np.testing.assert_allclose(resize_frames(video, size, method), expected, atol=1e-5)


def _predictor(model, **options) -> Predictor:
    return Predictor(model, device="cpu", capture="off", frames_per_call=1, **options)


@pytest.mark.parametrize(
    ("support", "backward"), [(None, False), ("local_and_grid", True), ("none", True)]
)
def test_tracker_matches_the_predictor(model, support, backward):
    video = np.random.default_rng(2).integers(0, 256, (14, 60, 80, 3), np.uint8)  # resized
    queries = np.array([[0, 10.0, 20.0], [5, 40.5, 33.0], [13, 79.0, 0.0]], np.float32)
    expected = _predictor(model, support_points=support).track(video, queries, backward=backward)
    tracker = OnnxTracker(graphs=EagerGraphs(model), support_points=support)
    got = tracker.track(video, queries, backward=backward)
    np.testing.assert_allclose(got.tracks, expected.tracks[0].numpy(), atol=2e-3, rtol=0)
    logits = expected.visibility_logits[0].numpy()
    np.testing.assert_allclose(got.visibility_logits, logits, atol=1e-3, rtol=0)
    firm = np.abs(logits - np.log(0.45 / 0.55)) > 1e-3
    assert (got.visibility == expected.visibility[0].numpy())[firm].all()
    np.testing.assert_array_equal(got.tracks[[0, 5, 13], [0, 1, 2]], queries[:, 1:])


def test_tracker_grid_and_errors(model):
    video = np.random.default_rng(3).integers(0, 256, (4, 48, 64, 3), np.uint8)
    expected = _predictor(model).track(video, grid_size=3, grid_query_frame=1)
    got = OnnxTracker(graphs=EagerGraphs(model)).track(video, grid_size=3, grid_query_frame=1)
    np.testing.assert_allclose(got.queries, expected.queries[0].numpy())
    np.testing.assert_allclose(got.tracks, expected.tracks[0].numpy(), atol=2e-3, rtol=0)
    tracker = OnnxTracker(graphs=EagerGraphs(model))
    with pytest.raises(ValueError, match="outside"):
        tracker.track(video, np.array([[4, 1.0, 1.0]]))
    with pytest.raises(ValueError, match="uint8"):
        tracker.track(video.astype(np.float32), np.array([[0, 1.0, 1.0]]))
    with pytest.raises(ValueError, match="exactly one"):
        tracker.track(video)


def _stream_run(online, start, frames, plan):
    """Feeds ``frames`` one at a time, adding and removing points as ``plan`` says.

    ``plan``: frame → ("add", queries) or ("remove", indices of earlier added ids).
    Returns tracks and logits per (frame, point id).
    """
    state = start()
    ids: list[int] = []
    tracks, logits = {}, {}

    def keep(update):
        for offset in range(update.tracks.shape[0]):
            for column, pid in enumerate(update.point_ids):
                frame = update.first_frame + offset
                tracks[frame, pid] = np.asarray(update.tracks[offset, column])
                logits[frame, pid] = float(update.visibility_logits[offset, column])

    for frame, image in enumerate(frames):
        for action, value in plan.get(frame, []):
            if action == "add":
                ids += online.add_queries(state, value)
            else:
                online.remove_queries(state, [ids[i] for i in value])
        keep(online.step(state, image))
    keep(online.finish(state))
    return tracks, logits


def _stream_plan(height: int, width: int) -> dict[int, list]:
    rng = np.random.default_rng(4)

    def points(frame: int, count: int) -> np.ndarray:
        xy = rng.uniform(0, [width - 1, height - 1], (count, 2))
        return np.concatenate([np.full((count, 1), frame), xy], 1).astype(np.float32)

    return {
        0: [("add", points(0, 3))],
        4: [("add", points(5, 2))],  # a later query frame, added ahead
        9: [("remove", [1]), ("add", points(9, 2))],
        15: [("remove", [0, 5])],
    }


def test_stream_matches_the_online_tracker(model):
    frames = np.random.default_rng(5).integers(0, 256, (20, 48, 64, 3), np.uint8)
    plan = _stream_plan(48, 64)
    online = OnlineTracker(_predictor(model))
    expected = _stream_run(online, lambda: online.start(frame_size=(48, 64)), frames, plan)
    onnx = OnnxOnlineTracker(OnnxTracker(graphs=EagerGraphs(model)))
    got = _stream_run(onnx, lambda: onnx.start(frame_size=(48, 64)), frames, plan)
    assert got[0].keys() == expected[0].keys()
    for key, value in expected[0].items():
        np.testing.assert_allclose(got[0][key], value, atol=2e-3, rtol=0)
        np.testing.assert_allclose(got[1][key], expected[1][key], atol=1e-3, rtol=0)


def test_stream_errors(model):
    onnx = OnnxOnlineTracker(OnnxTracker(graphs=EagerGraphs(model)))
    frames = np.zeros((3, 48, 64, 3), np.uint8)
    state = onnx.start(num_frames=2)
    with pytest.raises(ValueError, match="frame size is unknown"):
        onnx.add_queries(state, [[0, 1, 1]])
    onnx.step(state, frames[:2])
    with pytest.raises(FrameCountError):
        onnx.step(state, frames[2])
    with pytest.raises(ValueError, match="frame size changed"):
        onnx.step(onnx.start(frame_size=(40, 64)), frames[0])
    with pytest.raises(ValueError, match="unknown point ids"):
        onnx.remove_queries(state, [7])
    state = onnx.start()
    onnx.step(state, frames)  # frames 0 and 1 decoded
    with pytest.raises(ValueError, match="after frame 1"):
        onnx.add_queries(state, [[1, 2, 2]])


def test_command_refuses_torchscript_and_a_history_of_one(model, tmp_path, capsys):
    from taptr.cli.main import main
    from taptr.weights.checkpoint import save_checkpoint

    checkpoint = str(save_checkpoint(model, tmp_path / "v3.pth"))
    base = ["export", "--checkpoint", checkpoint, "--out", str(tmp_path / "out")]
    assert main([*base, "--format", "torchscript"]) == 2
    assert "TAPTRv3 exports to ONNX (--format onnx)" in capsys.readouterr().err
    assert main([*base, "--format", "onnx", "--history-frames", "1"]) == 2
    assert "--history-frames must be 0" in capsys.readouterr().err
    assert not (tmp_path / "out" / "decode_step.onnx").exists()


def test_manifest_round_trip_and_the_other_model_refused(model, tmp_path):
    from taptr.export.manifest import ExportManifest
    from taptr.onnx.v3_manifest import V3Manifest

    manifest = EagerGraphs(model, history_frames=16).manifest
    manifest.save(tmp_path)
    assert V3Manifest.load(tmp_path) == manifest
    assert manifest.history_frames == 16 and manifest.support.scheme == "grid"
    with pytest.raises(ValueError, match="TAPTRv3 export"):
        ExportManifest.load(tmp_path)
    with pytest.raises(FileNotFoundError, match="not a taptr export folder"):
        V3Manifest.load(tmp_path / "missing")
