"""The MLP's row-blocked inference equals the plain formulation and leaves training alone."""

import pytest
import torch

import taptr
from taptr.model.execution import EXECUTIONS, get_execution
from taptr.model.layers import MLP
from taptr.model.ops import ROW_BLOCK, blocked_mlp


def test_row_blocks_equal_all_rows_at_once():
    torch.manual_seed(0)
    mlp = MLP(16, 64, 8, num_layers=3)
    x = torch.randn(2, 333, 16)  # 666 rows: several blocks and a partial last one
    with torch.no_grad():
        blocked = mlp(x, row_block=100)
        plain = mlp(x)
        direct = blocked_mlp(mlp.layers, x.view(-1, 16), 100)
    assert blocked.shape == (2, 333, 8)
    torch.testing.assert_close(blocked, plain, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(direct, blocked.view(-1, 8), atol=0, rtol=0)


def test_row_blocks_are_skipped_when_autograd_records(monkeypatch):
    import taptr.model.layers as layers

    def fail(*args):
        raise AssertionError("row blocks under autograd")

    monkeypatch.setattr(layers, "blocked_mlp", fail)
    torch.manual_seed(0)
    mlp = MLP(4, 8, 2, num_layers=2)
    x = torch.randn(10, 4, requires_grad=True)
    mlp(x, row_block=3).square().sum().backward()
    assert x.grad is not None and all(p.grad is not None for p in mlp.parameters())


def test_executions_set_row_blocks():
    assert get_execution("fast").row_block == ROW_BLOCK
    assert get_execution("reference").row_block is None
    # training steps record autograd, so only its no-grad evaluation takes row blocks
    assert get_execution("training").row_block == ROW_BLOCK
    assert set(EXECUTIONS) == {"reference", "fast", "training"}


def test_the_model_hands_its_row_block_to_every_mlp(monkeypatch):
    import taptr.model.layers as layers

    seen = []
    original = layers.MLP.forward

    def spy(self, x, row_block=None):
        seen.append(row_block)
        return original(self, x, row_block)

    monkeypatch.setattr(layers.MLP, "forward", spy)
    model = taptr.build_model("tiny").eval()
    with torch.no_grad():
        for name, expected in (("fast", ROW_BLOCK), ("reference", None)):
            seen.clear()
            model.set_execution(name)
            features = model.encode_images(torch.zeros(1, 3, 64, 64))
            content = torch.zeros(1, 2, 3, 32)
            tracking = torch.ones(1, 2, 3, dtype=torch.bool)
            model.decode_window(
                features.memory[:, None].expand(1, 2, -1, -1),
                features.spatial_shapes,
                content,
                torch.zeros(1, 2, 3, 4),
                tracking,
                tracking,
            )
            model.update_content(content, content, content, tracking)
            assert seen and set(seen) == {expected}


def test_unknown_execution_names_the_choices():
    with pytest.raises(ValueError, match="unknown execution 'turbo'; choose from reference, fast"):
        get_execution("turbo")
    with pytest.raises(ValueError, match="unknown execution"):
        taptr.build_model("tiny", execution="turbo")
