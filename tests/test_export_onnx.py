"""ONNX export of the tiny preset: onnxruntime reproduces the PyTorch tracks.

The export takes about a minute on a 2-core CPU (mostly the exporter's own work on the
decoder graph), so one test exports once and checks everything; separate tests would
export once per pytest-xdist worker.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from taptr.config import tiny
from taptr.export.graph_runner import track_points
from taptr.export.graph_steps import OnnxSteps
from taptr.export.graphs import _wrappers, export_model, prepare_for_export
from taptr.export.manifest import GRAPHS, ExportManifest
from taptr.export.verify import sample_frames, torch_tracks
from tests.helpers import decode_window_inputs
from tests.test_export_runner import randomised

pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")


def test_onnx_export_of_tiny_matches_pytorch(tmp_path):
    model = randomised(tiny())
    export_model(model, tmp_path, "onnx")
    check_files(model, tmp_path)
    check_tracks(model, tmp_path, 11, [0, 3, 6, 9, 10])  # two windows, one point at the end
    check_tracks(model, tmp_path, 50, [0, 20, 31, 48])  # long video: content every 2nd window
    check_sizes(model, tmp_path, frames=1, window=1, points=1)
    check_sizes(model, tmp_path, frames=5, window=8, points=6)


def check_files(model, exported):
    manifest = ExportManifest.load(exported)
    assert manifest.format == "onnx" and manifest.opset == 18
    assert manifest.input_size == (64, 64)
    assert manifest.spatial_shapes == ((16, 16), (8, 8), (4, 4), (2, 2))
    assert (manifest.window_size, manifest.window_stride, manifest.d_model) == (8, 4, 32)
    assert all(manifest.graph_path(exported, name).is_file() for name in GRAPHS)
    assert model.execution.name == "fast"  # the model is untouched


def check_tracks(model, exported, num_frames, starts):
    frames = sample_frames(num_frames, (64, 64), seed=0)
    starts = np.array(starts, np.int64)
    positions = np.random.default_rng(0).uniform(0.05, 0.95, (len(starts), 2)).astype(np.float32)
    expected = torch_tracks(model, frames, starts, positions)  # the model's own gather kernel
    steps = OnnxSteps(exported, threads=1)
    got = track_points(steps, steps.manifest, frames, num_frames, starts, positions)
    assert np.abs(got.positions - expected.positions).max() <= 1e-4
    assert np.abs(got.visibility_logits - expected.visibility_logits).max() <= 1e-4


def check_sizes(model, exported, frames, window, points):
    """Graph by graph against the eager wrappers, at sizes other than the tracing examples."""
    steps = OnnxSteps(exported, threads=1)
    manifest = steps.manifest
    eager = _wrappers(prepare_for_export(model), manifest)
    generator = torch.Generator().manual_seed(points)
    video = torch.rand(frames, 3, 64, 64, generator=generator)
    memory = torch.rand(window, manifest.num_tokens, 32, generator=generator)
    positions = torch.rand(points, 2, generator=generator)
    starts = torch.arange(points) % (window + 1)  # some points start after the window
    decode_inputs = decode_window_inputs(memory, points, starts, generator)
    with torch.no_grad():
        expected = [
            [eager["encoder"](video)],
            [eager["init_points"](memory[0], positions)],
            list(eager["decode_window"](*decode_inputs)),
        ]
    got = [
        [steps.encode(video.numpy())],
        [steps.init_points(memory[0].numpy(), positions.numpy())],
        list(steps.decode(*(x.numpy() for x in decode_inputs))),
    ]
    for got_graph, expected_graph in zip(got, expected, strict=True):
        for value, reference in zip(got_graph, expected_graph, strict=True):
            assert value.shape == tuple(reference.shape)
            np.testing.assert_allclose(value, reference.numpy(), atol=2e-5, rtol=0)
