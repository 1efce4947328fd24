"""`taptr eval --protocol official` with TAPTRv3 reproduces the official v3 evaluation.

The fixture (tests/fixtures/v3_protocol_first.npz) holds every step of the authors'
``evaluate.py --streaming`` on one 12-frame DAVIS-format video with the seed-240716
ResNet-18 weights: the support points, the model input, the outputs and the metrics.
"""

from __future__ import annotations

import hashlib
import json
import pickle

import numpy as np
import pytest
import torch

from taptr.cli.main import main
from taptr.eval.official_protocol import (
    OfficialTAPTR,
    grid_draws,
    official_normalised,
    support_points_256,
)
from taptr.eval.protocols import OfficialProtocol
from taptr.eval.query_sampling import sample_queries
from taptr.types import TrackingSample
from tests.helpers import load_golden

METRICS = (
    "occlusion_accuracy",
    "average_jaccard",
    "average_pts_within_thresh",
    *(f"{name}_{d}" for d in (1, 2, 4, 8, 16) for name in ("jaccard", "pts_within")),
)


@pytest.fixture(scope="module")
def golden():
    return load_golden("v3_protocol_first")


@pytest.fixture(scope="module")
def clip(golden):
    sample = TrackingSample(
        video=golden["in_video_u8"],
        tracks=(golden["in_points"].transpose(1, 0, 2) * 256 - 0.5).astype(np.float32),
        visible=~golden["in_occluded"].T,
    )
    return OfficialProtocol(None).prepare(sample)


def test_support_points_and_model_input_match(golden, clip, official_v3_checkpoint):
    points = sample_queries(clip.tracks, clip.visible, "first")
    assert np.array_equal(points.queries[:, 0], golden["ds_query_frames"][:6])
    assert np.array_equal(grid_draws(0)[0], golden["ds_grid_r"])
    queries, kind = support_points_256(points.queries, grid_draws(0)[0])
    assert np.array_equal(kind, golden["ds_support_kind"])
    assert np.array_equal(queries[:, 0], golden["ds_query_frames"])
    expected_xy = golden["ds_query_points_tyx"][:, [2, 1]]
    assert np.abs(queries[:, 1:] - expected_xy).max() <= 1e-4  # real points: float32 GT × 255
    normalised = official_normalised(queries[:, 1:], (384, 512)).numpy()
    assert np.abs(normalised - golden["ds_query_xy_norm"]).max() <= 1e-6

    import taptr

    model = OfficialTAPTR(taptr.load_checkpoint(official_v3_checkpoint))
    model_input = model.model_input(golden["in_video_u8"]).numpy()
    assert list(model_input.shape) == golden["model_input_shape"].tolist()
    digest = hashlib.sha256(np.ascontiguousarray(model_input).tobytes()).hexdigest()
    flat = model_input.reshape(-1)[golden["model_input_sample_idx"]]
    assert digest == str(golden["model_input_sha256"]) or (
        np.abs(flat - golden["model_input_sample"]).max() <= 1e-5
    )


def test_taptr_eval_official_reproduces_the_metrics(golden, official_v3_checkpoint, tmp_path):
    root = tmp_path / "tapvid_davis"
    root.mkdir()
    entry = {
        "video": golden["in_video_u8"],
        "points": golden["in_points"],
        "occluded": golden["in_occluded"],
    }
    with open(root / "tapvid_davis.pkl", "wb") as stream:
        pickle.dump({str(golden["in_seq_name"]): entry}, stream)
    torch.set_num_threads(1)
    out = tmp_path / "out"
    code = main(
        [
            "eval",
            "--dataset",
            "davis",
            "--root",
            str(tmp_path),
            "--protocol",
            "official",
            "--checkpoint",
            str(official_v3_checkpoint),
            "--device",
            "cpu",
            "--out",
            str(out),
        ]
    )
    assert code in (0, None)
    report = json.loads((out / "results.json").read_text())
    video = report["videos"][0]
    for name in METRICS:
        assert video[name] == float(golden[f"metric_{name}"]), name
