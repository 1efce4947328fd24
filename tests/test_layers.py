"""The MLP's row-blocked inference equals the plain formulation and leaves training alone."""

import torch

import taptr
from taptr.model.layers import MLP, ROW_BLOCK
from taptr.model.paths import use_path


def test_row_blocks_equal_all_rows_at_once():
    torch.manual_seed(0)
    mlp = MLP(16, 64, 8, num_layers=3)
    x = torch.randn(2, 333, 16)  # 666 rows: several blocks and a partial last one
    mlp.row_block = 100
    with torch.no_grad():
        blocked = mlp(x)
        mlp.row_block = None
        plain = mlp(x)
    assert blocked.shape == (2, 333, 8)
    torch.testing.assert_close(blocked, plain, atol=1e-6, rtol=1e-6)


def test_row_blocks_are_skipped_when_autograd_records():
    torch.manual_seed(0)
    mlp = MLP(4, 8, 2, num_layers=2)
    mlp.row_block = 3
    x = torch.randn(10, 4, requires_grad=True)
    mlp(x).square().sum().backward()
    assert x.grad is not None and all(p.grad is not None for p in mlp.parameters())


def test_paths_switch_row_blocks():
    model = taptr.build_model("tiny")
    mlps = [m for m in model.modules() if isinstance(m, MLP)]
    assert mlps and all(m.row_block == ROW_BLOCK for m in mlps)
    use_path(model, "faithful")
    assert all(m.row_block is None for m in mlps)
    use_path(model, "fast")
    assert all(m.row_block == ROW_BLOCK for m in mlps)
