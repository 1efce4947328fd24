"""The official interactive demo reproduced by `Predictor` with the paper preset's defaults.

Fixture `demo_v2` (copied from the reference golden folder): the authors' `demo_inter.py`
run on a procedural clip with 4 clicks and the seed-1 generated weights, float32 on CPU.
The Predictor must rebuild the demo's model input bit for bit (Lanczos resize), its
800-point query set exactly (context points), and its tracks and visibility for the real
points. Clicks go in through the model's own normalised queries: taptr keeps pixel
centres at integers, the demo maps a click x to x·512/W (see docs/CONVENTIONS.md).
"""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
import torch

from taptr import Predictor
from taptr.api.context_points import draw_context, with_context
from taptr.api.resize import lanczos_resize
from taptr.geometry import pixels_to_normalized
from taptr.model.taptr import normalize_frames
from taptr.model.trajectory import QuerySet
from tests.helpers import FIXTURES


@pytest.fixture(scope="module")
def demo():
    case = np.load(FIXTURES / "demo_v2.npz")
    return {key: case[key] for key in case.files}


def real_queries(demo) -> np.ndarray:
    """(n, 3) (t, x, y) pixel queries: the demo's normalised clicks × (W − 1, H − 1)."""
    return np.concatenate([demo["real_start_t"][:, None], demo["real_xy_px"]], axis=1)


def test_fixture_is_the_official_demo_case(demo):
    conventions = json.loads(str(demo["conventions_json"]))
    assert conventions["case"] == "demo_v2"
    assert demo["in_frames"].shape == (16, 120, 160, 3) and len(demo["in_click_t"]) == 4


def test_lanczos_preprocessing_is_bit_exact(demo):
    frames = torch.from_numpy(demo["in_frames"]).permute(0, 3, 1, 2)
    model_input = normalize_frames(lanczos_resize(frames, (512, 512))).numpy()
    assert hashlib.sha256(model_input.tobytes()).hexdigest() == str(demo["pre_input_sha256"])
    np.testing.assert_array_equal(
        model_input.reshape(-1)[demo["pre_sample_idx"]], demo["pre_input_sample"]
    )


def test_context_points_are_the_official_800_point_set(demo):
    num_frames, height, width = demo["in_frames"].shape[:3]
    queries = torch.from_numpy(real_queries(demo)).float()
    real = QuerySet(
        queries[None, :, 0].long(),
        pixels_to_normalized(queries[None, :, 1:], height, width),
        torch.ones(1, len(queries), dtype=torch.bool),
    )
    padded = with_context(real, 800, (512, 512), num_frames)
    assert padded.positions.shape == (1, 800, 2)
    # the whole set, not only the first draw: an off-by-one in the bounds moves most points
    np.testing.assert_array_equal(padded.positions[0, 4:].numpy(), demo["q_xy_norm"][4:])
    np.testing.assert_allclose(padded.positions[0, :4].numpy(), demo["q_xy_norm"][:4], atol=1e-7)
    np.testing.assert_array_equal(padded.start_frames[0].numpy(), demo["q_query_frames"])
    assert bool(padded.start_visible.all())  # every official start label is 1
    np.testing.assert_array_equal(padded.start_frames[0, 4:].numpy(), demo["q_pad_prefix"])


def test_demo_padding_matches_the_512_space_recipe_whole(demo):
    clicks_512 = demo["q_xy_512"][:4].astype(np.float64)
    context = draw_context(clicks_512, 800, (512, 512), prefix_limit=min(12, 16))
    np.testing.assert_array_equal(context.positions, demo["q_xy_512"][4:])
    np.testing.assert_array_equal(context.start_frames, demo["q_pad_prefix"])


def test_predictor_reproduces_the_official_demo_tracks(demo, official_checkpoint):
    predictor = Predictor.from_pretrained(official_checkpoint, device="cpu")
    assert (predictor.context_points, predictor.resize) == (800, "lanczos")
    height, width = demo["in_frames"].shape[1:3]
    result = predictor.track(demo["in_frames"], real_queries(demo))
    ours = result.tracks[0].numpy() / np.array([width - 1, height - 1])  # (T, n, 2)
    written = demo["out_real_written"]  # (T, n): frames after each query frame
    error = np.abs(ours - demo["out_real_xy_norm"]).max(axis=-1)[written]
    assert error.max() <= 1e-4, error.max()
    official_logits = demo["out_vis_logits"][:, :4, 1]
    firm = written & (np.abs(official_logits) >= 1e-4)
    assert firm.sum() == written.sum()  # the fixture has no undecided real entries
    np.testing.assert_array_equal(
        result.visibility[0].numpy()[firm], demo["out_real_visible"][firm]
    )


@pytest.mark.slow
def test_without_context_the_demo_is_not_reproduced(demo, official_checkpoint):
    """The padding cannot be skipped: 800 → 0 context points moves the tracks by pixels."""
    predictor = Predictor.from_pretrained(official_checkpoint, device="cpu", context_points=0)
    height, width = demo["in_frames"].shape[1:3]
    frames = demo["in_frames"][:9]  # two windows are enough to show it
    result = predictor.track(frames, real_queries(demo))
    ours = result.tracks[0].numpy() / np.array([width - 1, height - 1])
    written = demo["out_real_written"][:9]
    error = np.abs(ours - demo["out_real_xy_norm"][:9]).max(axis=-1)[written]
    assert error.max() > 1e-3
