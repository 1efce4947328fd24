"""taptr calibrate: the threshold moves toward the one that scores best, and is stored and used."""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np
import pytest
import torch

import taptr
from taptr.cli.main import main as cli_main
from taptr.data.kubric import list_sequences, read_sequence, write_sequence
from taptr.data.sample_video import make_sample_clip
from taptr.eval.calibrate import choose_threshold, predict_videos, write_calibrated
from taptr.eval.datasets import open_dataset
from taptr.types import TrackingResult, TrackingSample
from taptr.weights.checkpoint import read_visibility_threshold, save_checkpoint


def _write_labelled_set(root, num_videos: int = 2, num_frames: int = 10, size: int = 256) -> None:
    """Sample clips with exact ground truth, in the Kubric layout."""
    for seed in range(num_videos):
        clip = make_sample_clip(num_frames=num_frames, height=size, width=size, seed=seed)
        grid = np.linspace(size * 0.1, size * 0.9, 4)
        queries = np.array([[0, x, y] for y in grid for x in grid])
        tracks, visible = clip.track(queries)
        write_sequence(root / f"{seed:05d}", TrackingSample(clip.video, tracks, visible))


class OraclePredictor:
    """Perfect positions and visibility decisions, with a visibility probability that is off.

    Visible points get probability ``p_visible``, occluded ones ``p_occluded``: a model
    whose ranking is right but whose probabilities are not calibrated.
    """

    def __init__(self, root, p_visible: float, p_occluded: float) -> None:
        self.truth = {}
        for folder in list_sequences(root):
            sample = read_sequence(folder)
            self.truth[hashlib.sha1(sample.video.tobytes()).hexdigest()] = sample
        self.logits = (
            math.log(p_visible / (1 - p_visible)),
            math.log(p_occluded / (1 - p_occluded)),
        )
        self.visibility_threshold = 0.5

    def track(self, video, queries, backward=False) -> TrackingResult:
        sample = self.truth[hashlib.sha1(np.ascontiguousarray(video).tobytes()).hexdigest()]
        queries = np.asarray(queries)
        frames = queries[:, 0].astype(int)
        # each query sits exactly on a ground-truth track at its query frame
        distance = np.linalg.norm(sample.tracks[frames] - queries[:, None, 1:], axis=-1)
        ids = distance.argmin(axis=1)
        tracks = torch.from_numpy(sample.tracks[:, ids])
        visible = torch.from_numpy(sample.visible[:, ids])
        logits = torch.where(visible, *map(torch.tensor, self.logits))
        return TrackingResult(tracks[None], visible[None], logits[None].float(), None)


@pytest.mark.parametrize(
    ("p_visible", "p_occluded", "direction"), [(0.32, 0.12, "down"), (0.88, 0.68, "up")]
)
def test_threshold_moves_toward_the_separating_value(tmp_path, p_visible, p_occluded, direction):
    _write_labelled_set(tmp_path)
    predictor = OraclePredictor(tmp_path, p_visible, p_occluded)
    predictions = predict_videos(predictor, open_dataset("kubric", tmp_path), "first")
    assert len(predictions) == 2 and all(p.gt_visible.size for p in predictions)
    for metric in ("aj", "oa"):
        result = choose_threshold(predictions, metric=metric, query_mode="first")
        # every threshold in [p_occluded, p_visible) separates perfectly; the nearest to 0.5 wins
        assert p_occluded <= result.threshold < p_visible
        assert result.threshold == (0.3 if direction == "down" else 0.7)
        assert result.score == pytest.approx(1.0)
        assert result.current == 0.5 and result.current_score < result.score
        assert len(result.thresholds) == len(result.scores) == 19


def test_ties_keep_the_current_threshold(tmp_path):
    _write_labelled_set(tmp_path, num_videos=1)
    predictor = OraclePredictor(tmp_path, 0.99, 0.01)  # any threshold in (0.01, 0.99) is perfect
    predictions = predict_videos(predictor, open_dataset("kubric", tmp_path), "strided")
    result = choose_threshold(predictions, query_mode="strided", current=0.42)
    assert result.threshold == 0.42 and 0.42 in result.thresholds
    with pytest.raises(ValueError, match="unknown metric"):
        choose_threshold(predictions, metric="delta")
    with pytest.raises(ValueError, match=r"lie in \(0, 1\)"):
        choose_threshold(predictions, thresholds=(0.0, 0.5))


def test_checkpoint_stores_and_predictor_uses_the_threshold(tmp_path):
    torch.manual_seed(0)
    model = taptr.build_model("tiny")
    plain = save_checkpoint(model, tmp_path / "plain.pth")
    assert read_visibility_threshold(plain) is None
    assert taptr.Predictor.from_pretrained(str(plain)).visibility_threshold == 0.5
    stored = save_checkpoint(model, tmp_path / "stored.pth", visibility_threshold=0.3)
    assert read_visibility_threshold(stored) == pytest.approx(0.3)
    assert taptr.Predictor.from_pretrained(stored).visibility_threshold == pytest.approx(0.3)
    explicit = taptr.Predictor.from_pretrained(stored, visibility_threshold=0.6)
    assert explicit.visibility_threshold == 0.6  # an explicit value wins
    with pytest.raises(ValueError, match="visibility_threshold"):
        save_checkpoint(model, tmp_path / "bad.pth", visibility_threshold=1.5)


def test_write_calibrated_keeps_the_other_entries(tmp_path):
    model = taptr.build_model("tiny")
    source = tmp_path / "run.pt"
    data = {**taptr.weights.checkpoint.checkpoint_dict(model, model.state_dict()), "step": 7}
    torch.save(data, source)
    out = write_calibrated(source, tmp_path / "calibrated.pt", 0.35)
    written = torch.load(out, weights_only=True)
    assert written["step"] == 7 and "ema" in written
    assert written["visibility_threshold"] == pytest.approx(0.35)
    write_calibrated(out, out, 0.4)  # in place
    assert read_visibility_threshold(out) == pytest.approx(0.4)
    official = tmp_path / "official.pth"
    torch.save({"ema_model": {"module.x": torch.zeros(1)}}, official)
    with pytest.raises(ValueError, match="not a taptr checkpoint"):
        write_calibrated(official, official, 0.3)  # never replaces the authors' file
    from_name = write_calibrated("tiny", tmp_path / "tiny.pth", 0.2)  # a preset name
    assert read_visibility_threshold(from_name) == pytest.approx(0.2)


def test_cli_calibrates_the_tiny_model(tmp_path, capsys):
    data = tmp_path / "data"
    _write_labelled_set(data, num_videos=1, num_frames=8, size=64)
    torch.manual_seed(0)
    checkpoint = save_checkpoint(taptr.build_model("tiny"), tmp_path / "tiny.pth")
    out, report = tmp_path / "calibrated.pth", tmp_path / "scores.json"
    argv = ["calibrate", "--checkpoint", str(checkpoint), "--dataset", "kubric"]
    argv += ["--root", str(data), "--out", str(out), "--json", str(report), "--device", "cpu"]
    assert cli_main([*argv, "--thresholds", "0.2", "0.8"]) == 0
    scores = json.loads(report.read_text())
    assert scores["thresholds"] == [0.2, 0.5, 0.8] and scores["metric"] == "aj"
    assert read_visibility_threshold(out) == pytest.approx(scores["threshold"])
    assert f"wrote {out}" in capsys.readouterr().out
    predictor = taptr.Predictor.from_pretrained(str(out), device="cpu")
    assert predictor.visibility_threshold == pytest.approx(scores["threshold"])
    assert cli_main([*argv, "--max-videos", "0"]) == 2
