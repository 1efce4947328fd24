"""Linear layers as oneDNN inner products (`taptr.model.ops.dense`): the same values as
``F.linear``, used by the fast execution only where they apply."""

import dataclasses

import pytest
import torch
import torch.nn.functional as F

import taptr
from taptr.model.execution import get_execution
from taptr.model.frame_tables import FrameTables
from taptr.model.ops.dense import linear, onednn_applies, onednn_available

ONEDNN_OP = "mkldnn::_linear_pointwise"

pytestmark = pytest.mark.cpu

needs_onednn = pytest.mark.skipif(
    not onednn_available(), reason="no oneDNN inner product on this CPU or build"
)


def _onednn_calls(run) -> int:
    """How many oneDNN inner products ``run()`` makes."""
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as profile:
        run()
    return sum(event.name == ONEDNN_OP for event in profile.events())


@needs_onednn
@pytest.mark.parametrize("relu", [False, True])
@pytest.mark.parametrize("with_bias", [False, True])
def test_onednn_linear_equals_f_linear(generator, relu, with_bias):
    x = torch.randn(3, 50, 24, generator=generator)
    weight = torch.randn(40, 24, generator=generator)
    bias = torch.randn(40, generator=generator) if with_bias else None
    expected = F.linear(x, weight, bias)
    if relu:
        expected = expected.relu()
    with torch.no_grad():
        assert _onednn_calls(lambda: linear(x, weight, bias, onednn=True, relu=relu)) == 1
        got = linear(x, weight, bias, onednn=True, relu=relu)
    assert got.shape == (3, 50, 40)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)
    if relu:  # the ReLU is applied: negatives of the product are zeroed
        assert bool((got >= 0).all()) and bool((got == 0).any())


@needs_onednn
def test_onednn_linear_takes_strided_rows_and_weights(generator):
    x = torch.randn(24, 60, generator=generator).t()[::2]  # (30, 24), column-major rows
    weight = torch.randn(24, 16, generator=generator).t()  # (16, 24), transposed storage
    with torch.no_grad():
        got = linear(x, weight, None, onednn=True)
    torch.testing.assert_close(got, F.linear(x, weight), rtol=1e-5, atol=1e-5)


class _Dense(torch.nn.Module):
    def __init__(self, weight: torch.Tensor) -> None:
        super().__init__()
        self.weight = torch.nn.Parameter(weight, requires_grad=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return linear(x, self.weight, None, onednn=True)


def test_f_linear_where_onednn_does_not_apply(generator):
    x = torch.randn(5, 8, generator=generator)
    weight = torch.randn(4, 8, generator=generator, requires_grad=True)
    # autograd records: oneDNN's op has no backward, so F.linear runs and gradients flow
    assert not onednn_applies(x, weight)
    assert _onednn_calls(lambda: linear(x, weight, None, onednn=True).sum().backward()) == 0
    assert weight.grad is not None
    with torch.no_grad():
        assert not onednn_applies(x.double(), weight.double())
        assert _onednn_calls(lambda: linear(x, weight, None, onednn=False)) == 0
        with torch.autocast("cpu", dtype=torch.bfloat16):
            assert not onednn_applies(x, weight)
    exported = torch.export.export(_Dense(weight.detach()), (x,))
    assert "mkldnn" not in str(exported.graph)  # a captured graph keeps F.linear
    relu = linear(x, weight.detach(), None, onednn=False, relu=True)
    torch.testing.assert_close(relu, F.linear(x, weight.detach()).relu())


@needs_onednn
def test_frame_tables_through_onednn_equal_the_blas_tables(generator):
    memory = torch.randn(2, 70, 16, generator=generator)
    key_proj, value_proj = torch.nn.Linear(16, 16), torch.nn.Linear(16, 16)
    tables = {}
    for onednn in (False, True):
        store = FrameTables()
        store.start_window(0, 1, keep_from=None)
        pairs = store.images(0, memory, key_proj, value_proj, onednn=onednn)
        tables[onednn] = [torch.stack(pair).clone() for pair in pairs]
    for blas, onednn in zip(tables[False], tables[True], strict=True):
        torch.testing.assert_close(onednn, blas, rtol=1e-5, atol=1e-5)
    with torch.no_grad():
        expected = torch.stack((key_proj(memory[1]), value_proj(memory[1])))
    torch.testing.assert_close(tables[True][1], expected, rtol=1e-5, atol=1e-5)


def _window(model, generator):
    """One encoded frame and a 2-frame decoder window on it, tiny sizes."""
    images = torch.randn(1, 3, 64, 64, generator=generator)
    points = 5
    content = torch.randn(1, 2, points, model.config.d_model, generator=generator)
    positions = torch.rand(1, 2, points, 4, generator=generator)
    tracking = torch.ones(1, 2, points, dtype=torch.bool)
    tracking[0, 0, :2] = False  # some points start later: grouped point attention

    def run():
        features = model.encode_images(images)
        memory = features.memory[:, None].expand(1, 2, -1, -1)
        out = model.decode_window(
            memory, features.spatial_shapes, content, positions, tracking, tracking
        )
        return features.memory, out.positions

    return run


@needs_onednn
def test_the_fast_execution_runs_its_products_through_onednn(generator):
    torch.manual_seed(0)
    model = taptr.build_model("tiny", execution="fast").eval()
    assert model.execution.onednn_linear and not get_execution("reference").onednn_linear
    run = _window(model, generator)
    with torch.no_grad():
        onednn_calls = _onednn_calls(run)
        memory, positions = run()
        model.set_execution(dataclasses.replace(get_execution("fast"), onednn_linear=False))
        assert _onednn_calls(run) == 0
        blas_memory, blas_positions = run()
    # every encoder and decoder product: far more than a handful of layers
    assert onednn_calls > 30
    torch.testing.assert_close(memory, blas_memory, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(positions, blas_positions, rtol=1e-5, atol=1e-5)


@needs_onednn
def test_flop_counter_counts_onednn_products_as_f_linear(generator):
    from torch.utils.flop_counter import FlopCounterMode

    x = torch.randn(3, 10, 8, generator=generator)
    weight, bias = torch.randn(6, 8, generator=generator), torch.randn(6, generator=generator)
    counts = []
    for onednn in (False, True):
        counter = FlopCounterMode(display=False)
        with torch.no_grad(), counter:
            linear(x, weight, bias, onednn=onednn, relu=True)
        counts.append(counter.get_total_flops())
    assert counts == [2 * 30 * 8 * 6] * 2


def test_row_blocks_keep_their_reused_buffers_where_onednn_does_not_apply(monkeypatch):
    import taptr.model.ops.row_blocks as row_blocks
    from taptr.model.layers import MLP
    from taptr.model.ops import blocked_mlp

    def fail(*args, **kwargs):
        raise AssertionError("per-block fresh products where oneDNN does not apply")

    monkeypatch.setattr(row_blocks, "apply_linear", fail)
    torch.manual_seed(0)
    mlp = MLP(8, 16, 4, num_layers=2).double()
    x = torch.randn(50, 8, dtype=torch.float64)  # float64: oneDNN's path does not apply
    with torch.no_grad():
        blocked = blocked_mlp(mlp.layers, x, 16, onednn=True)
        torch.testing.assert_close(blocked, mlp(x), rtol=1e-12, atol=1e-12)
