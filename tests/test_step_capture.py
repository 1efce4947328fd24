"""TAPTRv3's per-frame step captured and replayed (`taptr.runtime.step_capture`).

The decision is tested with a scripted clock and a stand-in for the compiled step (what
``auto`` does given what it measures); the capture itself with ``torch.compile``'s
``eager`` backend, which traces the step as Inductor would and runs it, through the
predictor and the online tracker, against the eager step.
"""

import logging
import math

import numpy as np
import pytest
import torch

from taptr.api.online import OnlineTracker
from taptr.api.predictor import Predictor
from taptr.model.build import build_model
from taptr.model.taptr import normalize_frames
from taptr.model.trajectory import QuerySet
from taptr.model.v3 import per_frame
from taptr.runtime import step_capture
from taptr.runtime.capture_buckets import BUCKET, pad_points, points_bucket
from taptr.runtime.frames import EncodedFrames
from taptr.runtime.measured import keep, kept_choice
from taptr.runtime.step_capture import CaptureTiming, StepCapture


@pytest.fixture(autouse=True)
def _own_measurements(tmp_path, monkeypatch):
    monkeypatch.setenv("TAPTR_MEASURED", str(tmp_path / "measured.json"))


class Clock:
    """A clock that moves only when the stand-in steps run."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _scripted(monkeypatch, clock, eager_s, captured_s, capture_s):
    """A decoder costing ``eager_s`` a call, and a captured step costing ``captured_s``
    (``capture_s`` more on its first call); returns the list of which ran."""
    ran = []

    def eager(*args):
        clock.now += eager_s
        ran.append("eager")
        return args[0]

    def captured(*args):
        clock.now += captured_s + (capture_s if "captured" not in ran else 0.0)
        ran.append("captured")
        return args[0]

    monkeypatch.setattr(step_capture, "captured_step", lambda decoder, device: captured)
    return eager, ran


def _key(points: int) -> str:
    return f"step {points_bucket(points)}"


def _run(step: StepCapture, frames: int) -> None:
    content = torch.zeros(1, 1, 5, 4)
    for _ in range(frames):
        step(content)


def test_a_long_run_measures_on_the_job_keeps_the_timing_and_captures(monkeypatch, caplog):
    clock = Clock()
    eager, ran = _scripted(monkeypatch, clock, eager_s=1.0, captured_s=0.5, capture_s=30.0)
    step = StepCapture(eager, torch.device("cpu"), "auto", _key, 5, 2000, clock=clock)
    with caplog.at_level(logging.WARNING, logger="taptr.runtime.step_capture"):
        _run(step, 20)
    # the stall of the capture is said before it happens (the stand-in is never kept)
    assert any("compiling TAPTRv3's per-frame step" in r.getMessage() for r in caplog.records)
    # 4 eager (the first one not counted), 4 captured (the first one paying the capture)
    assert ran[:4] == ["eager"] * 4 and ran[4:] == ["captured"] * 16
    timing = CaptureTiming.read(kept_choice(_key(5)))
    assert timing == CaptureTiming(1.0, 0.5, 30.0)


def test_a_capture_measured_slower_goes_back_to_the_eager_step(monkeypatch):
    clock = Clock()
    eager, ran = _scripted(monkeypatch, clock, eager_s=1.0, captured_s=1.2, capture_s=30.0)
    step = StepCapture(eager, torch.device("cpu"), "auto", _key, 5, 2000, clock=clock)
    _run(step, 12)
    assert ran[4:8] == ["captured"] * 4 and ran[8:] == ["eager"] * 4
    assert CaptureTiming.read(kept_choice(_key(5))).captured_s == pytest.approx(1.2)


def test_a_short_run_neither_measures_nor_captures(monkeypatch):
    clock = Clock()
    eager, ran = _scripted(monkeypatch, clock, eager_s=1.0, captured_s=0.5, capture_s=30.0)
    step = StepCapture(eager, torch.device("cpu"), "auto", _key, 5, 24, clock=clock)
    _run(step, 24)
    assert ran == ["eager"] * 24
    assert kept_choice(_key(5)) is None


@pytest.mark.parametrize(("frames", "expected"), [(100, "captured"), (50, "eager")])
def test_a_kept_timing_captures_only_when_the_frames_to_come_pay_for_it(
    monkeypatch, frames, expected
):
    # saves 0.5 s a frame, costs 40 s: worth it over 100 frames, not over 50
    keep(_key(5), {"eager_s": 1.0, "captured_s": 0.5, "capture_s": 40.0})
    clock = Clock()
    eager, ran = _scripted(monkeypatch, clock, eager_s=1.0, captured_s=0.5, capture_s=4.0)
    step = StepCapture(eager, torch.device("cpu"), "auto", _key, 5, frames, clock=clock)
    _run(step, 3)
    assert ran == [expected] * 3
    if expected == "captured":  # this process's capture cost replaces the kept one
        assert CaptureTiming.read(kept_choice(_key(5))).capture_s == pytest.approx(4.0)


def test_a_stream_of_unknown_length_never_stalls_to_measure(monkeypatch):
    clock = Clock()
    eager, ran = _scripted(monkeypatch, clock, eager_s=1.0, captured_s=0.5, capture_s=30.0)
    step = StepCapture(eager, torch.device("cpu"), "auto", _key, None, None, clock=clock)
    _run(step, 40)
    assert ran == ["eager"] * 40
    assert step.key == _key(5)  # read from the first call's content (B, 1, N, C)


def test_a_failed_capture_says_so_once_runs_eagerly_and_is_not_tried_again(monkeypatch, caplog):
    def broken(decoder, device):
        raise RuntimeError("no C++ compiler found\nmore detail")

    clock = Clock()
    eager, ran = _scripted(monkeypatch, clock, eager_s=1.0, captured_s=0.5, capture_s=30.0)
    monkeypatch.setattr(step_capture, "captured_step", broken)
    step = StepCapture(eager, torch.device("cpu"), "auto", _key, 5, 10**6, clock=clock)
    with caplog.at_level(logging.WARNING, logger="taptr.runtime.step_capture"):
        _run(step, 10)
    assert ran == ["eager"] * 10
    failures = [r.getMessage() for r in caplog.records if "failed" in r.getMessage()]
    assert len(failures) == 1 and "no C++ compiler found)" in failures[0]
    timing = CaptureTiming.read(kept_choice(_key(5)))
    assert math.isinf(timing.captured_s) and not timing.pays(10**9)


@pytest.mark.parametrize(
    "value",
    [
        None,
        "fast",
        {"eager_s": 1.0, "captured_s": 0.5},
        {"eager_s": 1.0, "captured_s": 0.5, "capture_s": -1.0},
        {"eager_s": float("nan"), "captured_s": 0.5, "capture_s": 1.0},
        {"eager_s": True, "captured_s": 0.5, "capture_s": 1.0},
    ],
)
def test_a_kept_value_that_is_no_timing_is_measured_again(value):
    assert CaptureTiming.read(value) is None


def test_points_are_padded_to_buckets():
    assert [points_bucket(n) for n in (1, BUCKET, BUCKET + 1)] == [BUCKET, BUCKET, 2 * BUCKET]


def _v3_run(model, queries, video, step=None):
    source = EncodedFrames(model, lambda a, b: normalize_frames(video[:, a : b + 1]), 1)
    with torch.no_grad():
        return per_frame.run_frames(
            model, queries, video.shape[1], source, torch.float64, step=step
        )


def test_padding_points_leaves_the_real_tracks_unchanged():
    torch.manual_seed(0)
    model = build_model("tiny-v3").double().eval()
    video = torch.rand(1, 5, 3, 64, 64, dtype=torch.float64)
    queries = QuerySet(
        torch.tensor([[0, 1, 0]]), torch.rand(1, 3, 2, dtype=torch.float64), torch.ones(1, 3).bool()
    )
    plain = _v3_run(model, queries, video)
    padded = _v3_run(model, pad_points(queries, 8), video)
    torch.testing.assert_close(padded.positions[:, :, :3], plain.positions, atol=1e-9, rtol=0)
    torch.testing.assert_close(
        padded.visibility_logits[:, :, :3], plain.visibility_logits, atol=1e-9, rtol=0
    )


@pytest.fixture
def eager_backend(monkeypatch):
    monkeypatch.setattr(step_capture, "BACKEND", "eager")
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()


def _predictor(capture, kernel="gather"):
    torch.manual_seed(0)
    model = build_model("tiny-v3")
    return Predictor(model, device="cpu", kernel=kernel, frames_per_call=1, capture=capture)


@pytest.mark.parametrize("kernel", ["gather", "grid_sample"])
def test_the_predictor_replays_a_captured_step_with_the_eager_tracks(eager_backend, kernel):
    rng = np.random.default_rng(0)
    video = rng.integers(0, 255, (6, 48, 48, 3), dtype=np.uint8)
    queries = np.array([[0, 10.0, 12.0], [1, 30.0, 20.0], [0, 24.0, 40.0]])
    eager = _predictor("off", kernel).track(video, queries)
    predictor = _predictor("on", kernel)
    steps = []
    original = predictor.runner.engine.step_for
    predictor.runner.engine.step_for = lambda *a: steps.append(original(*a)) or steps[-1]
    captured = predictor.track(video, queries)
    assert steps and steps[0].captured and steps[0].frames_left <= len(video) - 4
    np.testing.assert_allclose(captured.tracks, eager.tracks, atol=1e-4)
    np.testing.assert_array_equal(captured.visibility, eager.visibility)


def test_the_online_tracker_replays_a_captured_step_with_the_eager_tracks(eager_backend):
    rng = np.random.default_rng(1)
    video = rng.integers(0, 255, (5, 48, 48, 3), dtype=np.uint8)
    queries = np.array([[0, 10.0, 12.0], [0, 30.0, 20.0]])
    results = {}
    for capture in ("off", "on"):
        tracker = OnlineTracker(_predictor(capture))
        state = tracker.start(frame_size=(48, 48))
        tracker.add_queries(state, queries)
        updates = [tracker.step(state, video[t : t + 1]) for t in range(5)]
        updates.append(tracker.finish(state))
        results[capture] = np.concatenate([u.tracks for u in updates if len(u.tracks)])
    np.testing.assert_allclose(results["on"], results["off"], atol=1e-4)


def test_capture_is_checked():
    with pytest.raises(ValueError, match="capture must be one of auto, on, off"):
        _predictor("yes")
    with pytest.raises(ValueError, match="TAPTRv3 models only"):
        Predictor(build_model("tiny"), device="cpu", kernel="gather", capture="on")


@pytest.mark.cpu
def test_a_cpu_in_bfloat16_keeps_the_eager_step():
    from taptr.model.ops.dense import native_bfloat16

    if not native_bfloat16():
        pytest.skip("this CPU has no native bfloat16: the predictor runs float32")
    model = build_model("tiny-v3")
    predictor = Predictor(
        model,
        device="cpu",
        kernel="gather",
        frames_per_call=1,
        autocast=torch.bfloat16,
        capture="on",
    )
    assert predictor.runner.decoder_step(16, 100) is None
    assert _predictor("on").runner.decoder_step(16, 100).captured


def test_taptr_track_capture_on_writes_the_eager_tracks(eager_backend, tmp_path):
    from torch._dynamo.utils import counters

    from taptr.cli.main import main
    from taptr.io.video import write_video
    from taptr.weights.checkpoint import save_checkpoint

    torch.manual_seed(0)
    weights = save_checkpoint(build_model("tiny-v3"), tmp_path / "tiny_v3.pth")
    frames = np.random.default_rng(2).integers(0, 256, (6, 48, 64, 3), dtype=np.uint8)
    clip = write_video(tmp_path / "clip.mp4", frames, fps=10)
    tracks, graphs = {}, {}
    for capture in ("off", "on"):
        out = tmp_path / capture
        argv = ["track", str(clip), "--grid", "3", "--checkpoint", str(weights)]
        argv += ["--kernel", "gather", "--frames-per-call", "1", "--capture", capture]
        counters.clear()
        assert main([*argv, "--out", str(out)]) == 0
        tracks[capture] = np.load(out / "tracks.npz")["tracks"]
        graphs[capture] = counters["stats"]["unique_graphs"]
    assert graphs == {"off": 0, "on": 1}  # one graph for every frame
    np.testing.assert_allclose(tracks["on"], tracks["off"], atol=1e-3)


@pytest.mark.parametrize("case", ["v3_r18_small", "v3_r18_fifo"])
def test_the_captured_step_reproduces_the_official_golden_cases(
    eager_backend, official_v3_checkpoint, case
):
    import taptr
    from tests.helpers import golden_inputs, load_golden

    golden = load_golden(case)
    model = taptr.load_checkpoint(official_v3_checkpoint).eval()
    video, starts, xy, labels = golden_inputs(golden)
    queries = QuerySet(starts[None], xy[None], (labels == 1)[None])
    history = 16 if case == "v3_r18_fifo" else None
    outputs = {}
    for capture in ("off", "on"):
        step = StepCapture(model.decoder, torch.device("cpu"), capture, _key, 1, video.shape[1])
        with torch.no_grad():
            outputs[capture] = per_frame.run_frames(
                model,
                queries,
                video.shape[1],
                EncodedFrames(model, video),
                torch.float32,
                history_frames=history,
                step=step if capture == "on" else None,
            ).positions[0]
    assert step.captured and step.frames_left < video.shape[1] - 1
    # normalised positions: the captured step against the eager one, and the official code
    torch.testing.assert_close(outputs["on"], outputs["off"], atol=1e-5, rtol=0)
    official = torch.from_numpy(golden["out_pred_xy_norm"]).transpose(0, 1).float()
    assert float((outputs["on"] - official).abs().max()) <= 3e-5
