"""bfloat16 products on CPUs that have them: how far the golden cases move from float32.

`taptr.model.ops.dense.bfloat16_products` is what ``--dtype bfloat16`` runs on a CPU with
AVX512-BF16 or AMX. It must stay within what bfloat16 autocast moved the same cases when
it was first measured (docs/BENCHMARKS.md: 0.72 px on ``v2_long``); skipped elsewhere.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import taptr
from taptr.model.ops import dense
from tests.helpers import FIXTURES, golden_inputs, load_golden, seed1_official_weights

pytestmark = pytest.mark.skipif(
    not dense.native_bfloat16(), reason="this CPU has no native bfloat16 products"
)

BOUND_PX = 0.72


@pytest.fixture(scope="module")
def paper_model(tmp_path_factory):
    path = tmp_path_factory.mktemp("weights") / "taptrv2_seed1.pth"
    torch.save({"ema_model": seed1_official_weights("official-state-dict.txt")}, path)
    return taptr.load_checkpoint(path)


def _positions(model, golden, bfloat16: bool, **options) -> np.ndarray:
    context = dense.bfloat16_products() if bfloat16 else torch.inference_mode()
    with torch.no_grad(), context:
        out = taptr.official_forward(model, *golden_inputs(golden), **options)
    return out["positions"].numpy()


@pytest.mark.parametrize("case", ["v2_small_nonsquare", "v2_long"])
def test_golden_cases_stay_within_the_bfloat16_bound(paper_model, case):
    with np.load(FIXTURES / f"{case}.npz") as data:
        golden = {k: data[k] for k in data.files}
    height, width = golden["in_video_u8"].shape[-2:]
    exact = _positions(paper_model, golden, bfloat16=False)
    rounded = _positions(paper_model, golden, bfloat16=True)
    moved = np.abs(rounded - exact) * np.array([width - 1, height - 1])
    assert 0 < moved.max() <= BOUND_PX  # products did run in bfloat16, and stay close
    assert np.median(moved) < 0.05


@pytest.mark.parametrize(
    "case, history, percentile",
    # 40 frames of random weights amplify any rounding: there one point in a hundred may
    # move further (max 1.05 px; bfloat16 autocast 1.18), docs/BENCHMARKS.md
    [("v3_r18_small", None, 100), ("v3_r18_fifo", 16, 99)],
)
def test_taptrv3_golden_cases_stay_within_the_bfloat16_bound(
    official_v3_checkpoint, case, history, percentile
):
    model = taptr.load_checkpoint(official_v3_checkpoint)
    golden = load_golden(case)
    height, width = golden["in_video_u8"].shape[-2:]
    exact = _positions(model, golden, bfloat16=False, history_frames=history)
    rounded = _positions(model, golden, bfloat16=True, history_frames=history)
    moved = np.abs(rounded - exact) * np.array([width - 1, height - 1])
    assert 0 < np.percentile(moved, percentile) <= BOUND_PX
    assert np.median(moved) < 0.05


def test_the_copies_follow_their_weights():
    weight = torch.randn(8, 4)
    first = dense._bfloat16_copy(weight)
    assert dense._bfloat16_copy(weight) is first  # made once
    weight.mul_(2)  # an in-place change (load_state_dict) makes a new copy
    torch.testing.assert_close(dense._bfloat16_copy(weight).float(), weight, rtol=1e-2, atol=0)
    key = id(weight)
    del weight
    assert key not in dense._BFLOAT16_COPIES


def test_products_come_back_in_float32_except_between_mlp_layers():
    x, weight, bias = torch.randn(5, 4), torch.randn(3, 4), torch.randn(3)
    with torch.no_grad(), dense.bfloat16_products():
        out = dense.linear(x, weight, bias, onednn=True)
        hidden = dense.linear(x, weight, bias, onednn=True, relu=True, hidden=True)
    assert out.dtype == torch.float32 and hidden.dtype == torch.bfloat16
    exact = torch.nn.functional.linear(x, weight, bias)
    torch.testing.assert_close(out, exact, rtol=0.05, atol=0.05)
    assert (hidden >= 0).all()
