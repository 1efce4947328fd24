"""Frames per encoder call: read-ahead in `EncodedFrames`, the measured choice, its memory."""

from __future__ import annotations

import copy

import pytest
import torch

import taptr
from taptr.api.predictor import Predictor
from taptr.runtime import encode_choice, measured
from taptr.runtime.encode_choice import (
    candidates,
    choose_frames_per_call,
    fastest,
    time_frames_per_call,
)
from taptr.runtime.frames import EncodedFrames
from taptr.runtime.measured import remembered
from taptr.runtime.measured_file import read_choices

CPU = torch.device("cpu")
QUERIES = torch.tensor([[0, 10.0, 20.0], [3, 40.0, 30.0], [5, 70.0, 50.0]])


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return taptr.build_model("tiny").eval()


@pytest.fixture(scope="module")
def video():
    generator = torch.Generator().manual_seed(2)
    return torch.rand(1, 12, 3, 32, 48, generator=generator)


@pytest.fixture
def measured_file(tmp_path, monkeypatch):
    path = tmp_path / "measured.json"
    monkeypatch.setenv("TAPTR_MEASURED", str(path))
    return path


class _Counting:
    """Wraps a model's ``encode`` to record the frames each call receives."""

    def __init__(self, model, monkeypatch):
        self.calls: list[int] = []
        encode = model.encode

        def counted(frames, chunk_size=None):
            self.calls.append(frames.shape[1])
            return encode(frames, chunk_size)

        monkeypatch.setattr(model, "encode", counted)


def _windows(source, num_frames, window=8, stride=4):
    first = 0
    while True:
        last = min(first + window - 1, num_frames - 1)
        yield source(first, last).memory
        if last == num_frames - 1:
            return
        first += stride


@torch.no_grad()
def test_reading_ahead_encodes_full_chunks_and_the_same_memory(model, video, monkeypatch):
    one = [m.clone() for m in _windows(EncodedFrames(model, video), 12)]
    counting = _Counting(model, monkeypatch)
    source = EncodedFrames(model, video, chunk_size=5)
    for expected, memory in zip(one, _windows(source, 12), strict=True):
        torch.testing.assert_close(memory, expected, atol=1e-5, rtol=1e-5)
        assert len(source.cache) <= 8 + 5  # a window and a chunk read ahead
    # frames 0-4, 5-9 (the first window asks for 0-7), 10-11 (the video ends)
    assert counting.calls == [5, 5, 2]


@torch.no_grad()
def test_a_stream_is_never_read_past_the_window_it_asked_for(model, video, monkeypatch):
    asked: list[tuple[int, int]] = []

    def load(first, last):
        asked.append((first, last))
        return video[:, first : last + 1]

    source = EncodedFrames(model, load, chunk_size=16)  # no length: a stream
    list(_windows(source, 12))
    assert asked == [(0, 7), (8, 11)]


def test_candidates_fit_the_devices_pixel_budget():
    assert candidates(CPU, (512, 512)) == [1]  # as before: one frame at a time
    assert candidates(CPU, (256, 256)) == [1, 2]
    assert candidates(CPU, (128, 128)) == [1, 2, 4, 8]
    assert candidates(torch.device("cuda"), (512, 512)) == [1, 2, 4, 8, 16]
    assert candidates(torch.device("cuda"), (1024, 1024)) == [1, 2, 4]
    # an 8 GB GPU: a call's trunk activations (168 MB a frame) within an eighth of it
    frame = 4 * 512 * 512 * 160
    assert candidates(torch.device("cuda"), (512, 512), frame, 8 * 1024**3) == [1, 2, 4]


def test_the_fewest_frames_within_the_tolerance_win():
    assert fastest({1: 1.0, 2: 0.99, 4: 0.5, 8: 0.49}) == 4
    assert fastest({1: 1.0, 2: 0.98}) == 1  # 2% faster is not worth a second frame's memory
    assert fastest({1: 1.0, 2: 1.2}) == 1


def test_timing_is_per_frame(model):
    ticks = iter(range(100))
    seconds = time_frames_per_call(
        model, CPU, (32, 48), [1, 4], repeats=2, clock=lambda: next(ticks)
    )
    assert seconds == {1: 1.0, 4: 0.25}  # one tick per call, over the call's frames


def test_auto_measures_once_per_shape_then_remembers(model, measured_file, monkeypatch):
    monkeypatch.setattr(
        encode_choice, "time_frames_per_call", lambda *a, **k: {1: 3.0, 2: 2.0, 4: 1.0}
    )
    assert choose_frames_per_call(model, CPU, (32, 48)) == 4
    entries = read_choices(measured_file).choices
    (key,) = entries
    assert "frames per encoder call" in key and "32x48" in key and entries[key] == 4

    def fail(*args, **kwargs):
        pytest.fail("measured again")

    monkeypatch.setattr(encode_choice, "time_frames_per_call", fail)
    assert choose_frames_per_call(model, CPU, (32, 48)) == 4
    assert choose_frames_per_call(model, CPU, (512, 512)) == 1  # one candidate: no timing
    assert choose_frames_per_call(model, CPU, (32, 48), 3) == 3
    for wrong in (0, -1, True, "many", 2.5):
        with pytest.raises(ValueError, match="frames per call must be"):
            choose_frames_per_call(model, CPU, (32, 48), wrong)


def test_the_precision_is_part_of_the_key(model, measured_file, monkeypatch):
    values = iter([{1: 1.0, 2: 0.5}, {1: 0.5, 2: 1.0}])
    monkeypatch.setattr(encode_choice, "time_frames_per_call", lambda *a, **k: next(values))
    assert choose_frames_per_call(model, CPU, (32, 48)) == 2
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert choose_frames_per_call(model, CPU, (32, 48)) == 1
    assert len(read_choices(measured_file).choices) == 2


def test_a_broken_or_unwritable_file_costs_only_the_measurement(tmp_path):
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    with pytest.warns(UserWarning, match="not taptr's file"):
        assert remembered("k", lambda: 5, broken) == 5
    assert broken.read_text() == "{not json"  # not taptr's: left alone
    empty = tmp_path / "empty.json"
    empty.write_text("")
    assert remembered("k", lambda: 6, empty) == 6
    assert read_choices(empty).choices == {"k": 6}
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    assert remembered("k", lambda: 7, blocked / "measured.json") == 7  # parent is a file


def test_keys_name_the_machine_torch_and_shape(monkeypatch):
    monkeypatch.setattr(measured, "cpu_name", lambda: "Some CPU")
    key = measured.choice_key("what", CPU, "config", "32x48")
    assert key.startswith("what | Some CPU (")
    assert f"torch {torch.__version__}" in key and key.endswith("| 32x48")
    assert measured.choice_key("what", CPU, "other config", "32x48") != key


def test_measured_path_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("TAPTR_MEASURED", str(tmp_path / "m.json"))
    assert measured.measured_path() == tmp_path / "m.json"
    monkeypatch.delenv("TAPTR_MEASURED")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert measured.measured_path() == tmp_path / "taptr" / "measured.json"


def test_the_predictor_tracks_the_same_at_any_frames_per_call(model, measured_file):
    frames = torch.rand(1, 10, 3, 64, 80, generator=torch.Generator().manual_seed(3)) * 255
    video = frames.to(torch.uint8)
    one = Predictor(copy.deepcopy(model), device="cpu", frames_per_call=1)
    four = Predictor(copy.deepcopy(model), device="cpu", frames_per_call=4)
    assert (one.frames_per_call, four.frames_per_call) == (1, 4)
    first, second = one.track(video, QUERIES), four.track(video, QUERIES)
    torch.testing.assert_close(second.tracks, first.tracks, atol=1e-3, rtol=0)
    finite = first.visibility_logits.isfinite()  # -inf before each query's frame
    assert torch.equal(second.visibility_logits.isfinite(), finite)
    torch.testing.assert_close(
        second.visibility_logits[finite], first.visibility_logits[finite], atol=1e-3, rtol=0
    )
    auto = Predictor(copy.deepcopy(model), device="cpu")
    assert auto.frames_per_call in candidates(CPU, auto.input_size)
    assert read_choices(measured_file).choices  # the choice was remembered
    with pytest.raises(ValueError, match="frames per call must be"):
        Predictor(copy.deepcopy(model), device="cpu", frames_per_call=0)


@torch.no_grad()
def test_a_stream_reads_ahead_through_arrived_frames_only(model, video, monkeypatch):
    from taptr.runtime.frames import StreamFrames

    counting = _Counting(model, monkeypatch)
    frames = StreamFrames(model, frames_per_call=4)
    frames.add(0, video[:, :10])
    frames(0, 7)
    assert counting.calls == [4, 4]  # frames 8 and 9 wait: a chunk would need 8-11
    frames(4, 9)
    assert counting.calls == [4, 4, 2]  # only 8 and 9 have arrived
    frames.add(10, video[:, 10:12])
    assert len(frames) == 2 + 6  # waiting 10, 11; encoded 4-9
    streamed = frames(8, 11).memory
    assert counting.calls[-1] == 2  # 10 and 11 in one call
    expected = EncodedFrames(model, video)(8, 11).memory
    torch.testing.assert_close(streamed, expected, atol=1e-5, rtol=1e-5)


def test_best_seconds_skips_the_first_call_and_keeps_the_fastest():
    calls, ticks = [], iter([0.0, 5.0, 10.0, 12.0, 20.0, 23.0])
    seconds = measured.best_seconds(lambda: calls.append(1), CPU, 3, clock=lambda: next(ticks))
    assert len(calls) == 4 and seconds == 2.0  # 5, 2 and 3 ticks: the warm-up is not timed
