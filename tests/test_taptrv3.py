"""TAPTRv3 around the golden cases: checkpoints, the driver, its history, streaming, support."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

import taptr
from taptr.api.online import OnlineTracker
from taptr.api.support import grid_positions, local_offsets, with_support
from taptr.model.sliding_window import run_windows
from taptr.model.trajectory import QuerySet
from taptr.model.v3 import TAPTRv3, per_frame
from taptr.model.v3.history import History, frame_weights
from taptr.runtime.frames import EncodedFrames
from taptr.weights.checkpoint import CheckpointError, checkpoint_contents
from tests.helpers import generated_official_weights, load_golden, noise_video


@pytest.fixture(scope="module")
def tiny_v3() -> TAPTRv3:
    torch.manual_seed(0)
    model = taptr.build_model("tiny-v3").eval()
    assert isinstance(model, TAPTRv3)
    return model


def _queries(points: int, frames: int, seed: int = 0) -> QuerySet:
    generator = torch.Generator().manual_seed(seed)
    return QuerySet(
        torch.randint(0, max(1, frames // 2), (1, points), generator=generator),
        torch.rand(1, points, 2, generator=generator, dtype=torch.float64),
        torch.ones(1, points, dtype=torch.bool),
    )


def _video(frames: int, size=(48, 64), seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.randn(1, frames, 3, *size, generator=generator, dtype=torch.float64)


def _run(model, video, queries, history_frames=None):
    with torch.no_grad():
        return per_frame.run_frames(
            model,
            queries,
            video.shape[1],
            EncodedFrames(model, video),
            video.dtype,
            history_frames=history_frames,
        )


# --- released checkpoints --------------------------------------------------------------


@pytest.mark.parametrize(
    ("key_list", "preset"),
    [
        ("official-v3-r18-state-dict.txt", "taptrv3"),
        ("official-v3-r50-state-dict.txt", "taptrv3-r50"),
    ],
)
def test_official_files_are_told_apart_by_their_keys(key_list, preset):
    weights = generated_official_weights(key_list, seed=3)
    config, converted = checkpoint_contents({"ema_model": weights}, "release.pth")
    assert config == taptr.get_config(preset)
    assert len(converted) == len(weights) - 32  # the aliased heads are dropped
    # the stored rotary tables are kept as they are, not regenerated
    freqs = [k for k in converted if k.endswith("long_temporal.rotary.freqs")]
    assert len(freqs) == 4


def test_official_v3_file_loads_strictly_and_keeps_its_rotary_table(tmp_path):
    weights = generated_official_weights("official-v3-r18-state-dict.txt", seed=5)
    key = "module.transformer.decoder.layers.2.lta_temporal_embedding.freqs"
    weights[key] = weights[key] * (1 + 1e-6)  # what an EMA's rounding might leave
    path = tmp_path / "TAPTRv3_resnet18_384x512.pth"
    torch.save({"ema_model": weights}, path)
    model = taptr.load_checkpoint(path)
    assert isinstance(model, TAPTRv3) and model.config == taptr.get_config("taptrv3")
    assert torch.equal(model.decoder.layers[2].long_temporal.rotary.freqs, weights[key])

    del weights["module.transformer.decoder.layers.1.norm_ltemp.bias"]
    torch.save({"ema_model": weights}, path)
    with pytest.raises(
        CheckpointError, match=r"missing \(1\): decoder.layers.1.norm_long_temporal"
    ):
        taptr.load_checkpoint(path)


def test_a_saved_web_page_is_named_as_one(tmp_path):
    page = tmp_path / "TAPTRv3_resnet18_384x512.pth"
    page.write_text(
        "<!DOCTYPE html><html><head><title>Google Drive - Virus scan warning</title></head>"
        "<body>Google Drive can't scan this file for viruses.</body></html>"
    )
    with pytest.raises(CheckpointError, match=r"web page.*browser"):
        taptr.load_checkpoint(page)


def test_named_v3_models_say_where_to_get_them(tmp_path, monkeypatch):
    monkeypatch.setenv("TAPTR_WEIGHTS_DIR", str(tmp_path))
    for name, link in (
        ("taptrv3-official", "1frPX9R_nKDG8FmL-vH6l_2HsJfhvEjtg"),
        ("taptrv3-r50-official", "19iql2VTqGIeoyg_wt3JjpohszN5UE6s1"),
    ):
        with pytest.raises(FileNotFoundError) as error:
            taptr.from_pretrained(name)
        message = str(error.value)
        assert link in message and "non-commercial" in message and str(tmp_path) in message
        assert "\n" not in message


def test_named_v3_model_is_read_from_the_weights_folder(
    tmp_path, monkeypatch, official_v3_checkpoint
):
    monkeypatch.setenv("TAPTR_WEIGHTS_DIR", str(tmp_path))
    (tmp_path / "TAPTRv3_resnet18_384x512.pth").symlink_to(official_v3_checkpoint)
    predictor = taptr.Predictor.from_pretrained("taptrv3-official", device="cpu")
    assert isinstance(predictor.model, TAPTRv3)
    assert predictor.visibility_threshold == 0.45
    assert predictor.input_size == (384, 512)


# --- the per-frame driver ----------------------------------------------------------------


def test_fast_execution_equals_reference(tiny_v3):
    video, queries = _video(10), _queries(7, 10)
    model = copy.deepcopy(tiny_v3).double()
    reference = _run(model.set_execution("reference"), video, queries)
    fast = _run(model.set_execution("fast"), video, queries)
    torch.testing.assert_close(fast.layer_positions, reference.layer_positions, atol=1e-9, rtol=0)
    torch.testing.assert_close(
        fast.layer_visibility_logits, reference.layer_visibility_logits, atol=1e-8, rtol=0
    )


def test_history_limit_at_the_length_changes_nothing_and_below_it_does(tiny_v3):
    video, queries = _video(12), _queries(5, 12)
    model = copy.deepcopy(tiny_v3).double()
    whole = _run(model, video, queries)
    assert torch.equal(_run(model, video, queries, history_frames=12).positions, whole.positions)
    limited = _run(model, video, queries, history_frames=4)
    assert not torch.allclose(limited.positions, whole.positions)


def test_points_are_never_written_before_they_are_tracked(tiny_v3):
    video = _video(8)
    queries = QuerySet(
        torch.tensor([[0, 3, 7]]),
        torch.tensor([[[0.2, 0.3], [0.5, 0.5], [0.9, 0.1]]]).double(),
        torch.tensor([[True, False, True]]),
    )
    out = _run(copy.deepcopy(tiny_v3).double(), video, queries)
    start = out.visibility_logits[0, :, :, 1]  # (T, N)
    frames = torch.arange(8)[:, None]
    starts = queries.start_frames
    # visible (+6.9) on the start frame, occluded (−6.9) before it, whatever the label
    assert torch.allclose(start[frames == starts], torch.full((3,), 6.9077554), atol=1e-5)
    assert torch.allclose(start[frames < starts], torch.tensor(-6.9077554), atol=1e-5)
    before = out.positions[0][frames <= starts]  # (K, 2) at the start position
    expected = queries.positions[0].expand(8, 3, 2)[frames <= starts]
    assert (before - expected).abs().max() < 1e-12


def test_the_window_driver_refuses_a_v3_model(tiny_v3):
    with pytest.raises(TypeError, match="frame by frame"):
        run_windows(
            tiny_v3, _queries(2, 4), 4, EncodedFrames(tiny_v3, _video(4).float()), torch.float32
        )


def test_history_holds_the_last_frames_when_limited():
    like = torch.zeros(1, dtype=torch.float64)
    history = History(1, 2, limit=3, like=like)
    history.add_points(1)
    for frame in range(20):
        history.open_frame(frame, torch.full((1, 1, 2), -1.0).double(), torch.zeros(1, 1))
        history.close_frame(
            torch.full((1, 1, 2), float(frame)).double(),
            torch.full((1, 1), 1.0 * frame),
            torch.ones(1, 1, dtype=torch.bool),
        )
        assert history.frames().tolist() == list(range(max(0, frame - 2), frame + 1))
        assert history.content[0, 0, :, 0].tolist() == [float(f) for f in history.frames()]
    unlimited = History(1, 2, limit=0, like=like)
    unlimited.add_points(1)
    for frame in range(40):
        unlimited.open_frame(frame, torch.zeros(1, 1, 2).double(), torch.zeros(1, 1))
    assert unlimited.length == 40 and unlimited.first == 0


def test_history_limit_longer_than_the_clip_allocates_only_the_frames_seen():
    """Issue 37.1: a limit of 10^9 (or 100,000) held buffers sized at the limit."""
    like = torch.zeros(1)
    limited, unlimited = History(2, 16, limit=10**9, like=like), History(2, 16, limit=0, like=like)
    for history in (limited, unlimited):
        history.add_points(3)
        for frame in range(6):
            history.open_frame(frame, torch.full((2, 3, 16), float(frame)), torch.zeros(2, 3))
    assert limited._content.shape[2] == unlimited._content.shape[2] == 8  # grown by doubling
    assert torch.equal(limited.content, unlimited.content)


def test_predictor_with_a_history_limit_of_100000_tracks_like_without(tiny_v3):
    video = noise_video(8, seed=3)[:, :40, :56]
    limited = _predictor(tiny_v3, history_frames=100_000).track(video, QUERIES)
    whole = _predictor(tiny_v3, history_frames=0).track(video, QUERIES)
    torch.testing.assert_close(limited.tracks, whole.tracks, rtol=0, atol=0)


@pytest.mark.parametrize("history_frames", [0, 3])
def test_static_shapes_read_the_whole_buffer_with_the_same_result(tiny_v3, history_frames):
    """The static step (every buffer slot, empty ones at weight 0) equals the exact one."""
    video, queries, model = _video(11), _queries(6, 11), copy.deepcopy(tiny_v3).double()
    with torch.no_grad():
        runs = [
            per_frame.run_frames(
                model,
                queries,
                11,
                EncodedFrames(model, video),
                video.dtype,
                history_frames=history_frames,
                static_shapes=static,
            )
            for static in (False, True)
        ]
    torch.testing.assert_close(runs[1].positions, runs[0].positions, atol=1e-6, rtol=0)
    torch.testing.assert_close(
        runs[1].visibility_logits, runs[0].visibility_logits, atol=1e-5, rtol=0
    )


def test_frame_weights_follow_the_official_mask():
    frames = torch.arange(5)
    logits = torch.tensor([[[0.0, 0.0, 2.0, -1.0, -6.9077554]]])
    weights = frame_weights(frames, torch.tensor([[1]]), logits, weighted=True)[0, 0]
    expected = torch.tensor(
        [0.0, 1.0, torch.sigmoid(torch.tensor(2.0)), torch.sigmoid(torch.tensor(-1.0)), 0.000999]
    )
    torch.testing.assert_close(weights, expected, atol=1e-6, rtol=0)
    allowed = frame_weights(frames, torch.tensor([[1]]), logits, weighted=False)[0, 0]
    assert allowed.tolist() == [False, True, True, True, True]


# --- the user path -------------------------------------------------------------------------


def _predictor(model, **kwargs):
    return taptr.Predictor(copy.deepcopy(model), device="cpu", dtype=torch.float64, **kwargs)


QUERIES = np.array([[0, 10, 20], [3, 40, 30], [6, 5, 5]], np.float32)


@pytest.mark.parametrize("support", ["grid", "local_and_grid"])
def test_stream_equals_offline_with_points_added_mid_stream(tiny_v3, support):
    predictor = _predictor(tiny_v3, support_points=support)
    video = noise_video(14, seed=2)[:, :40, :56]
    offline = predictor.track(video, QUERIES)
    online = OnlineTracker(predictor)
    state = online.start(frame_size=(40, 56))
    online.add_queries(state, QUERIES[:1])
    updates = []
    for frame in range(14):
        updates.append(online.step(state, video[frame]))
        # one frame of latency: every frame but the newest is final
        assert state.emitted == frame
        for t, x, y in QUERIES[1:]:
            if frame == t:  # a point clicked on the newest frame joins on time
                online.add_queries(state, [[t, x, y]])
    updates.append(online.finish(state))
    assert sum(u.tracks.shape[0] for u in updates) == 14
    for update in updates:
        frames = slice(update.first_frame, update.first_frame + update.tracks.shape[0])
        points = len(update.point_ids)
        expected = offline.tracks[0, frames, :points]
        torch.testing.assert_close(update.tracks, expected, atol=1e-6, rtol=0)
        assert torch.equal(update.visibility, offline.visibility[0, frames, :points])


def test_support_points_follow_the_official_pattern():
    offsets = local_offsets()
    assert offsets.shape == (63, 2)
    assert not ((offsets[:, 0] == -24) & np.isclose(offsets[:, 1], 24 / 7)).any()  # the quirk
    assert grid_positions()[[0, 5, 35]].tolist() == [[16, 16], [239, 16], [239, 239]]
    queries = QuerySet(
        torch.tensor([[4, 2]]),
        torch.tensor([[[0.5, 0.5], [0.1, 0.9]]]),
        torch.ones(1, 2, dtype=torch.bool),
    )
    padded = with_support(queries, "local_and_grid")
    assert padded.start_frames.shape == (1, 2 + 2 * 63 + 36)
    assert padded.start_frames[0, 2:65].eq(4).all() and padded.start_frames[0, 65:128].eq(2).all()
    torch.testing.assert_close(
        padded.positions[0, 2], torch.tensor([0.5 - 24 / 255, 0.5 - 24 / 255])
    )
    assert with_support(queries, "grid").start_frames.shape == (1, 38)


def test_predictor_defaults_follow_the_v3_config(tiny_v3):
    predictor = _predictor(tiny_v3)
    assert predictor.visibility_threshold == 0.45
    model = copy.deepcopy(tiny_v3)
    model.config = model.config.replace(support_points="local_and_grid")
    predictor = _predictor(model)
    assert predictor.support_scheme(32) == "local_and_grid"
    assert predictor.support_scheme(33) == "grid"  # 1,000 queries would be 64,036 points
    assert (
        _predictor(model, support_points="local_and_grid").support_scheme(1000) == "local_and_grid"
    )
    with pytest.raises(ValueError, match="history_frames"):
        _predictor(model, history_frames=1)


def test_history_frames_is_refused_for_v2(tiny_model):
    with pytest.raises(ValueError, match="TAPTRv3"):
        taptr.Predictor(tiny_model, device="cpu", history_frames=8)
    golden = load_golden("v2_small_nonsquare")
    with pytest.raises(ValueError, match="TAPTRv3"):
        taptr.official_forward(
            tiny_model,
            torch.zeros(1, 2, 3, 32, 32),
            torch.tensor([0]),
            torch.tensor([[0.5, 0.5]]),
            history_frames=4,
        )
    assert golden  # the fixture exists for the v2 cases next to these


def test_removing_a_point_removes_its_local_support(tiny_v3):
    predictor = _predictor(tiny_v3, support_points="local_and_grid")
    online = OnlineTracker(predictor)
    state = online.start(frame_size=(40, 56))
    ids = online.add_queries(state, QUERIES[:2])
    video = noise_video(4, seed=3)[:, :40, :56]
    online.step(state, video[:2])  # frame 0 is decoded: the support is drawn
    assert int(state.is_context.sum()) == 2 * 63 + 36
    online.remove_queries(state, [ids[0]])
    assert int(state.is_context.sum()) == 63 + 36 and state.point_ids == [ids[1]]
    assert online.engine.queries(state.tracker).start_frames.shape[1] == 1 + 63 + 36
    online.step(state, video[2:])
    assert online.finish(state).tracks.shape[1] == 1
