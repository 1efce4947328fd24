"""Context points: the official padding recipe, and how the predictor and streams use it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import taptr
from taptr.api.context_points import ContextPoints, draw_context, padding_bounds, with_context
from taptr.api.online import OnlineTracker
from taptr.config import ModelConfig, get_config
from taptr.eval.official_protocol import official_padding
from taptr.model.trajectory import QuerySet
from taptr.train.config import from_dict as train_config_from_dict


def spec_padding(real: np.ndarray, count: int, low: int, high: int, prefix: int):
    """TAPTRv2-SPEC §4.2 / §6 written as literally as possible, on numpy's global generator."""
    state = np.random.get_state()
    np.random.seed(0)
    listed = [list(p) for p in real]
    while len(listed) < count - len(real):
        candidate = np.random.randint(low, high + 1, size=2)
        if all(np.linalg.norm(np.array(p) - candidate) >= 1 for p in listed):
            listed.append(list(candidate))
    kept = np.array(listed[-(count - len(real)) :], dtype=np.float64)
    prefixes = np.random.randint(0, prefix, count - len(real))
    np.random.set_state(state)
    return kept, prefixes


@pytest.mark.parametrize(
    ("real", "frames"),
    [(np.zeros((0, 2)), 24), (np.array([[10.5, 20.25], [100.0, 3.0], [30.0, 240.0]]), 30)],
)
def test_evaluation_padding_is_the_whole_256_space_set(real, frames):
    padding = official_padding(real, frames, num_queries=300)
    positions, prefixes = spec_padding(real, 300, 16, 239, 12)
    np.testing.assert_array_equal(padding.positions, positions)
    np.testing.assert_array_equal(padding.start_frames, prefixes)


def test_evaluation_padding_pins_the_800_point_set():
    """A fingerprint of the full 797-point evaluation set (any change to the draws shows)."""
    real = np.array([[10.5, 20.25], [100.0, 3.0], [30.0, 240.0]])
    padding = official_padding(real, 24)
    positions, prefixes = spec_padding(real, 800, 16, 239, 12)
    np.testing.assert_array_equal(padding.positions, positions)
    np.testing.assert_array_equal(padding.start_frames, prefixes)
    assert padding.positions[3:].sum() == 202_350.0 and int(padding.start_frames.sum()) == 4_414


def test_bounds_are_a_sixteenth_margin():
    assert [b.tolist() for b in padding_bounds((512, 512))] == [[32, 32], [479, 479]]
    assert [b.tolist() for b in padding_bounds((256, 256))] == [[16, 16], [239, 239]]
    low, high = padding_bounds((64, 128))
    assert low.tolist() == [8, 4] and high.tolist() == [119, 59]


def test_non_square_frames_draw_inside_their_own_bounds():
    context = draw_context(np.zeros((0, 2)), 200, (64, 128), prefix_limit=5)
    assert context.positions[:, 0].min() >= 8 and context.positions[:, 0].max() <= 119
    assert context.positions[:, 1].min() >= 4 and context.positions[:, 1].max() <= 59
    assert context.start_frames.max() < 5


def test_nothing_is_drawn_when_the_real_points_fill_the_set():
    context = draw_context(np.ones((10, 2)), 10, (512, 512), prefix_limit=12)
    assert context == ContextPoints(context.positions, context.start_frames)
    assert context.positions.shape == (0, 2) and context.start_frames.shape == (0,)


def _queries(n: int) -> QuerySet:
    positions = torch.rand(1, n, 2, generator=torch.Generator().manual_seed(n))
    return QuerySet(
        torch.zeros(1, n, dtype=torch.long), positions, torch.ones(1, n, dtype=torch.bool)
    )


def test_with_context_appends_after_the_real_points():
    real = _queries(3)
    padded = with_context(real, 20, (64, 64), num_frames=5)
    assert padded.positions.shape == (1, 20, 2)
    assert torch.equal(padded.positions[:, :3], real.positions)
    assert int(padded.start_frames.max()) < 5  # drawn from [0, min(12, T))
    assert with_context(real, 3, (64, 64), 5) is real


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return taptr.build_model("tiny")


def _video(frames: int = 10) -> np.ndarray:
    return (np.random.default_rng(0).random((frames, 40, 56, 3)) * 255).astype(np.uint8)


QUERIES = np.array([[0, 10, 20], [3, 55, 39], [6, 5, 5]], np.float32)


def test_context_points_change_the_tracks_but_are_never_returned(model):
    plain = taptr.Predictor(model, device="cpu", context_points=0).track(_video(), QUERIES)
    padded = taptr.Predictor(model, device="cpu", context_points=24).track(_video(), QUERIES)
    assert padded.tracks.shape == plain.tracks.shape == (1, 10, 3, 2)
    assert padded.visibility.shape == (1, 10, 3)
    assert not torch.allclose(padded.tracks, plain.tracks)  # points attend to each other


def test_context_equals_the_model_run_on_the_padded_set(model):
    """The predictor's real points are exactly the first rows of a run on the padded set."""
    from taptr.official.model_forward import official_forward

    predictor = taptr.Predictor(model, device="cpu", context_points=16, dtype=torch.float64)
    video = _video()
    result = predictor.track(video, QUERIES)
    frames = torch.from_numpy(video).permute(0, 3, 1, 2)
    real = QuerySet(
        torch.from_numpy(QUERIES[None, :, 0]).long(),
        torch.from_numpy(QUERIES[None, :, 1:] / np.array([55, 39], np.float32)).double(),
        torch.ones(1, 3, dtype=torch.bool),
    )
    padded = with_context(real, 16, predictor.input_size, 10)
    output = official_forward(
        model.double(), predictor.prepare(frames), padded.start_frames[0], padded.positions[0]
    )
    model.float()
    positions = output["positions"][:, :3].float() * torch.tensor([55.0, 39.0])
    later = torch.arange(10)[:, None] > torch.from_numpy(QUERIES[:, 0])[None]
    torch.testing.assert_close(result.tracks[0][later], positions[later], atol=1e-4, rtol=0)


def test_enough_user_points_add_nothing(model):
    many = np.concatenate([QUERIES] * 4)  # 12 points ≥ 8 context points
    plain = taptr.Predictor(model, device="cpu", context_points=0).track(_video(), many)
    padded = taptr.Predictor(model, device="cpu", context_points=8).track(_video(), many)
    assert torch.equal(plain.tracks, padded.tracks)


@pytest.mark.parametrize("bad", [-1, 2.5, True, "800"])
def test_bad_context_counts_are_refused(model, bad):
    with pytest.raises(ValueError, match="context_points"):
        taptr.Predictor(model, device="cpu", context_points=bad)


def test_counts_come_from_the_config():
    assert (
        get_config("taptrv2").context_points == 800 and get_config("taptrv1").context_points == 800
    )
    assert (get_config("taptrv2").resize, get_config("small").resize) == ("lanczos", "bilinear")
    assert get_config("small").context_points == 128 and get_config("tiny").context_points == 0
    # files written before the fields existed were used without context, resized bilinearly
    legacy = {
        k: v
        for k, v in get_config("small").to_dict().items()
        if k not in ("context_points", "resize")
    }
    restored = ModelConfig.from_dict(legacy)
    assert (restored.context_points, restored.resize) == (0, "bilinear")
    with pytest.raises(ValueError, match="resize"):
        get_config("tiny").replace(resize="nearest")


def test_trained_models_keep_their_points_per_clip():
    config = train_config_from_dict({"preset": "small", "data": {"num_points": 64}})
    assert config.model.context_points == 64
    explicit = train_config_from_dict({"preset": "small", "model": {"context_points": 0}})
    assert explicit.model.context_points == 0


@pytest.mark.parametrize(("frames", "declare"), [(20, True), (20, False), (9, True)])
def test_stream_with_context_equals_offline(model, frames, declare):
    predictor = taptr.Predictor(model, device="cpu", dtype=torch.float64, context_points=12)
    video = _video(frames)
    queries = QUERIES.copy()
    offline = predictor.track(video, queries)
    online = OnlineTracker(predictor)
    state = online.start(num_frames=frames if declare else None, frame_size=(40, 56))
    online.add_queries(state, queries)
    updates = [online.step(state, video[i]) for i in range(frames)] + [online.finish(state)]
    tracks = torch.cat([u.tracks for u in updates if u.tracks.shape[0]])
    assert tracks.shape == (frames, 3, 2) and int(state.is_context.sum()) == 9
    torch.testing.assert_close(tracks, offline.tracks[0], atol=1e-6, rtol=0)
    model.float()


def test_stream_removes_user_points_and_keeps_context(model):
    predictor = taptr.Predictor(model, device="cpu", context_points=10)
    online = OnlineTracker(predictor)
    state = online.start(frame_size=(40, 56))
    ids = online.add_queries(state, QUERIES)
    video = _video(16)
    for frame in range(10):
        online.step(state, video[frame])
    online.remove_queries(state, [ids[0]])
    extra = online.add_queries(state, [[12, 30.0, 30.0]])
    for frame in range(10, 16):
        online.step(state, video[frame])
    final = online.finish(state)
    assert final.point_ids == [ids[1], ids[2], extra[0]] and final.tracks.shape[1] == 3
    assert int(state.is_context.sum()) == 7 and len(state.is_context) == 10


def test_evaluation_can_track_a_few_points_per_call(model):
    from taptr.eval.predictor_tracker import PredictorTracker

    predictor = taptr.Predictor(model, device="cpu", context_points=0)
    video = _video()
    grouped = PredictorTracker(predictor, backward=False, points_per_call=2)
    tracks, visible = grouped.track(video, QUERIES)
    first = predictor.track(video, QUERIES[:2])
    last = predictor.track(video, QUERIES[2:])
    np.testing.assert_array_equal(tracks[:, :2], first.tracks[0].numpy())
    np.testing.assert_array_equal(tracks[:, 2:], last.tracks[0].numpy())
    np.testing.assert_array_equal(visible[:, 2:], last.visibility[0].numpy())
    whole, _ = PredictorTracker(predictor, backward=False).track(video, QUERIES)
    assert not np.allclose(whole, tracks)  # the points of one call attend to each other
    with pytest.raises(ValueError, match="points_per_call"):
        PredictorTracker(predictor, backward=False, points_per_call=0)


def test_eval_flags_reach_the_predictor(tmp_path):
    from taptr.cli.main import build_parser
    from taptr.eval.runner import EvalConfig, build_protocol
    from taptr.weights.checkpoint import save_checkpoint

    path = save_checkpoint(taptr.build_model("tiny"), tmp_path / "tiny.pth")
    args = build_parser().parse_args(
        ["eval", "--dataset", "davis", "--root", "x.pkl", "--out", str(tmp_path / "o")]
        + ["--context-points", "5", "--points-per-call", "3"]
    )
    config = EvalConfig(
        dataset="davis",
        root="x.pkl",
        checkpoint=str(path),
        context_points=args.context_points,
        points_per_call=args.points_per_call,
    )
    tracker = build_protocol(config, "cpu").tracker
    assert (tracker.predictor.context_points, tracker.points_per_call) == (5, 3)
