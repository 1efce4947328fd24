"""TorchScript export of the tiny preset, and the ``taptr export`` command."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from taptr.api.predictor import Predictor
from taptr.cli.main import main
from taptr.config import tiny
from taptr.data.sample_video import make_sample_clip
from taptr.export.graph_runner import track_points
from taptr.export.graph_steps import TorchScriptSteps, load_steps
from taptr.export.graphs import _wrappers, export_model, prepare_for_export
from taptr.export.manifest import GRAPHS, ExportManifest
from taptr.export.track_video import track_video
from taptr.export.verify import sample_frames, torch_tracks
from taptr.weights.checkpoint import save_checkpoint
from tests.helpers import decode_window_inputs
from tests.test_export_runner import randomised


@pytest.fixture(scope="module")
def model():
    return randomised(tiny())


@pytest.fixture(scope="module")
def exported(model, tmp_path_factory):
    directory = tmp_path_factory.mktemp("torchscript")
    export_model(model, directory, "torchscript")
    return directory


def test_torchscript_tracks_match_pytorch(model, exported):
    frames = sample_frames(11, (64, 64), seed=0)
    starts = np.array([0, 3, 6, 9, 10], np.int64)
    positions = np.random.default_rng(0).uniform(0.05, 0.95, (5, 2)).astype(np.float32)
    expected = torch_tracks(model, frames, starts, positions)
    steps = load_steps(exported)
    assert isinstance(steps, TorchScriptSteps)
    got = track_points(steps, steps.manifest, frames, 11, starts, positions)
    assert np.abs(got.positions - expected.positions).max() <= 1e-4
    assert np.abs(got.visibility_logits - expected.visibility_logits).max() <= 1e-4


def test_traced_graphs_are_not_tied_to_the_example_sizes(model, exported):
    steps = load_steps(exported)
    eager = _wrappers(prepare_for_export(model), steps.manifest)
    generator = torch.Generator().manual_seed(0)
    window, points = 7, 9
    memory = torch.rand(window, steps.manifest.num_tokens, 32, generator=generator)
    inputs = decode_window_inputs(memory, points, torch.arange(points) % 8, generator)
    with torch.no_grad():
        expected = eager["decode_window"](*inputs)
        video = torch.rand(3, 3, 64, 64, generator=generator)
        np.testing.assert_allclose(
            steps.encode(video.numpy()), eager["encoder"](video).numpy(), atol=1e-5
        )
    for value, reference in zip(steps.decode(*(x.numpy() for x in inputs)), expected, strict=True):
        np.testing.assert_allclose(value, reference.numpy(), atol=1e-5, rtol=0)


def test_pixel_runner_matches_the_predictor(model, exported):
    clip = make_sample_clip(num_frames=10, height=64, width=64)  # at the input size: no resize
    queries = np.array([[0, 10.0, 20.0], [4, 33.5, 40.0], [9, 63.0, 0.0]], np.float32)
    expected = Predictor(model, device="cpu").track(clip.video, queries)
    steps = load_steps(exported)
    tracks, visible = track_video(steps, steps.manifest, clip.video, queries)
    np.testing.assert_allclose(tracks, expected.tracks[0].numpy(), atol=64e-4, rtol=0)
    np.testing.assert_array_equal(visible, expected.visibility[0].numpy())
    np.testing.assert_array_equal(tracks[[0, 4, 9], [0, 1, 2]], queries[:, 1:])
    larger = make_sample_clip(num_frames=4, height=90, width=120).video
    tracks, visible = track_video(steps, steps.manifest, larger, queries[:1])
    assert tracks.shape == (4, 1, 2) and visible.shape == (4, 1)


def test_cli_exports_and_checks(model, tmp_path, capsys):
    checkpoint = save_checkpoint(model, tmp_path / "tiny.pth")
    out = tmp_path / "exported"
    status = main(
        [
            "export",
            "--format",
            "torchscript",
            "--out",
            str(out),
            "--checkpoint",
            str(checkpoint),
            "--input-size",
            "48",
            "80",
            "--check",
            "--check-frames",
            "9",
            "--check-points",
            "3",
        ]
    )
    printed = capsys.readouterr().out
    assert status == 0
    assert ExportManifest.load(out).input_size == (48, 80)
    assert all((out / f"{name}.pt").is_file() for name in GRAPHS)
    assert "80×48 frames" in printed and "check on the 9-frame sample clip" in printed
    error = float(printed.split("max |Δ| positions ")[1].split()[0])
    assert error <= 1e-4


def test_cli_rejects_an_unknown_format(capsys):
    with pytest.raises(SystemExit):
        main(["export", "--format", "tflite", "--out", "x"])
    assert "invalid choice" in capsys.readouterr().err
