"""The exported-graph backend of the window driver gives the model's own tracks.

The graphs run here over the eager export wrappers (no export), so that every bookkeeping
rule is checked quickly: window ranges, skipped windows, initialisation at the start
frame, write-back and padding, the long-video content rule, v1's memory-efficient mode.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import taptr
from taptr.config import tiny
from taptr.export.graph_runner import track_points
from taptr.export.graphs import _manifest, _wrappers, prepare_for_export
from taptr.export.verify import torch_tracks
from tests.helpers import tiny_v1


class EagerSteps:
    """`taptr.export.graph_runner.Steps` over the PyTorch wrappers, before any export."""

    def __init__(self, model):
        prepared = prepare_for_export(model)
        self.manifest = _manifest(prepared, "torchscript", None, None)
        self.modules = _wrappers(prepared, self.manifest)

    def _run(self, name, *inputs):
        with torch.no_grad():
            outputs = self.modules[name](*(torch.from_numpy(np.asarray(x)) for x in inputs))
        return (
            outputs.numpy() if isinstance(outputs, torch.Tensor) else [o.numpy() for o in outputs]
        )

    def encode(self, frames):
        return self._run("encoder", frames)

    def init_points(self, memory, positions):
        return self._run("init_points", memory, positions)

    def decode(self, *inputs):
        return tuple(self._run("decode_window", *inputs))


def randomised(config) -> taptr.model.taptr.TAPTR:
    """A seeded model whose zero-initialised parameters (position heads) are non-zero."""
    torch.manual_seed(0)
    model = taptr.build_model(config).eval()
    with torch.no_grad():
        for param in model.parameters():
            if not param.any():
                param.normal_(0, 0.1)
    return model


@pytest.fixture(scope="module")
def tiny_random():
    return randomised(tiny())


def _frames(num_frames, seed=0):
    rng = np.random.default_rng(seed)
    return rng.random((num_frames, 3, 64, 64), dtype=np.float32)


@pytest.mark.parametrize(
    "num_frames,starts",
    [
        (11, [0, 2, 5, 9, 10]),  # two windows; a point on the very last frame
        (5, [0, 3, 4]),  # shorter than a window
        (50, [0, 13, 30, 47, 49]),  # long video: content handed over every 2nd window
        (20, [12, 19]),  # the first windows have nothing to update and are skipped
    ],
)
def test_reference_loop_matches_run_windows(tiny_random, num_frames, starts):
    frames = _frames(num_frames)
    starts = np.array(starts, np.int64)
    positions = np.random.default_rng(1).uniform(0.05, 0.95, (len(starts), 2)).astype(np.float32)
    expected = torch_tracks(tiny_random, frames, starts, positions)
    steps = EagerSteps(tiny_random)
    got = track_points(steps, steps.manifest, frames, num_frames, starts, positions)
    np.testing.assert_allclose(got.positions, expected.positions, atol=1e-5, rtol=0)
    np.testing.assert_allclose(got.visibility_logits, expected.visibility_logits, atol=1e-4)


def test_start_visibility_sets_unwritten_frames(tiny_random):
    frames = _frames(9)
    steps = EagerSteps(tiny_random)
    starts, positions = np.array([0, 8]), np.full((2, 2), 0.5, np.float32)
    got = track_points(
        steps, steps.manifest, frames, 9, starts, positions, start_visible=np.array([True, False])
    )
    # the second point starts on the last frame: no window updates it
    np.testing.assert_array_equal(got.visibility_logits[:, 1], np.tile([0, 0, 1], (9, 1)))
    np.testing.assert_allclose(got.positions[:, 1], 0.5, atol=1e-6)


def test_frames_from_a_loader(tiny_random):
    frames = _frames(11)
    steps = EagerSteps(tiny_random)
    starts, positions = np.array([0, 6]), np.full((2, 2), 0.3, np.float32)
    asked = []

    def load(first, last):
        asked.append((first, last))
        return frames[first : last + 1]

    from_array = track_points(steps, steps.manifest, frames, 11, starts, positions)
    from_loader = track_points(steps, steps.manifest, load, 11, starts, positions)
    np.testing.assert_array_equal(from_array.positions, from_loader.positions)
    assert asked == [(0, 7), (8, 10)]  # every frame is encoded once


def test_v1_memory_efficient_mode():
    config = tiny_v1(memory_efficient=True)
    model = randomised(config)
    frames = _frames(14)
    starts = np.array([0, 4, 10, 13], np.int64)  # two of them start after frame 7
    positions = np.random.default_rng(2).uniform(0.1, 0.9, (4, 2)).astype(np.float32)
    expected = torch_tracks(model, frames, starts, positions)
    steps = EagerSteps(model)
    assert steps.manifest.memory_efficient and steps.manifest.version == 1
    got = track_points(steps, steps.manifest, frames, 14, starts, positions)
    np.testing.assert_allclose(got.positions, expected.positions, atol=1e-5, rtol=0)


def test_frames_of_the_wrong_size_are_refused(tiny_random):
    steps = EagerSteps(tiny_random)
    frames = np.zeros((9, 3, 32, 64), np.float32)
    with pytest.raises(ValueError, match=r"\(F, 3, 64, 64\)"):
        track_points(steps, steps.manifest, frames, 9, np.array([0]), np.full((1, 2), 0.5))
