"""The fast execution's inference-only variants equal the plain formulation: row-blocked MLPs
and encoder layers, the decoder's key and value tables made per frame, channels-last
frames."""

import dataclasses

import pytest
import torch

import taptr
from taptr.config import get_config
from taptr.model.execution import EXECUTIONS, get_execution
from taptr.model.layers import MLP
from taptr.model.ops import ROW_BLOCK, blocked_mlp
from taptr.model.ops.row_blocks import ENCODER_BLOCK


@pytest.mark.parametrize("onednn", [False, True])
def test_row_blocks_equal_all_rows_at_once(onednn):
    torch.manual_seed(0)
    mlp = MLP(16, 64, 8, num_layers=3)
    x = torch.randn(2, 333, 16)  # 666 rows: several blocks and a partial last one
    with torch.no_grad():
        blocked = mlp(x, _fast(row_block=100, onednn_linear=onednn))
        plain = mlp(x)
        direct = blocked_mlp(mlp.layers, x.view(-1, 16), 100, onednn)
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
    mlp(x, _fast(row_block=3)).square().sum().backward()
    assert x.grad is not None and all(p.grad is not None for p in mlp.parameters())


def test_executions_set_row_blocks():
    assert get_execution("fast").row_block == ROW_BLOCK
    assert get_execution("reference").row_block is None
    # training steps record autograd, so only its no-grad evaluation takes row blocks
    assert get_execution("training").row_block == ROW_BLOCK
    assert set(EXECUTIONS) == {"reference", "fast", "training"}
    # the encoder's blocks and the shared decoder tables are the fast execution's alone
    assert [(e.encoder_block, e.shared_tables) for e in EXECUTIONS.values()] == [
        (None, False),
        (ENCODER_BLOCK, True),
        (None, False),
    ]


def test_the_model_hands_its_execution_to_every_mlp(monkeypatch):
    import taptr.model.layers as layers

    seen = []
    original = layers.MLP.forward

    def spy(self, x, execution=None):
        seen.append(None if execution is None else execution.name)
        return original(self, x, execution)

    monkeypatch.setattr(layers.MLP, "forward", spy)
    model = taptr.build_model("tiny").eval()
    with torch.no_grad():
        for name in ("fast", "reference"):
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
            assert seen and set(seen) == {name}


def test_unknown_execution_names_the_choices():
    with pytest.raises(ValueError, match="unknown execution 'turbo'; choose from reference, fast"):
        get_execution("turbo")
    with pytest.raises(ValueError, match="unknown execution"):
        taptr.build_model("tiny", execution="turbo")


def _fast(**changes):
    return dataclasses.replace(get_execution("fast"), **changes)


def test_encoder_layers_take_the_tokens_in_row_blocks(monkeypatch, generator):
    from taptr.model.attention import DeformableAttention

    blocks = []
    original = DeformableAttention.attend

    def spy(self, query, *args):
        blocks.append(query.shape[1])
        return original(self, query, *args)

    monkeypatch.setattr(DeformableAttention, "attend", spy)
    torch.manual_seed(0)
    model = taptr.build_model("tiny").eval()
    images = torch.rand(2, 3, 64, 64, generator=generator)
    layers = len(model.encoder.layers)
    with torch.no_grad():
        plain = model.set_execution(_fast(encoder_block=None)).encode_images(images)
        tokens = sum(h * w for h, w in plain.spatial_shapes)
        assert blocks == [tokens] * layers and tokens == 340
        blocks.clear()
        blocked = model.set_execution(_fast(encoder_block=100)).encode_images(images).memory
    assert blocks == [100, 100, 100, 40] * layers  # every block attends to the whole frame
    torch.testing.assert_close(blocked, plain.memory, atol=1e-5, rtol=0)
    blocks.clear()
    model.encode_images(images).memory.sum().backward()  # autograd records: all rows at once
    assert blocks == [tokens] * layers


def test_decoder_layers_take_their_tables_from_a_frame_store(monkeypatch, generator):
    from taptr.model.decoder import Decoder
    from taptr.model.frame_tables import FrameTables

    torch.manual_seed(0)
    model = taptr.build_model("tiny").eval()
    features = model.encode_images(torch.rand(2, 3, 64, 64, generator=generator))
    memory = features.memory[None]  # (1, W_t = 2, S, C)
    content = torch.randn(1, 2, 3, 32, generator=generator)
    positions = torch.randn(1, 2, 3, 4, generator=generator)
    tracking = torch.ones(1, 2, 3, dtype=torch.bool)
    args = (memory, features.spatial_shapes, content, positions, tracking, tracking)
    store = FrameTables()
    store.start_window(10, 11, keep_from=11)
    with torch.no_grad():
        throwaway = model.decode_window(*args)  # a store of its own that keeps nothing
        kept = model.decode_window(*args, store)
        assert store.projections == 2 * model.num_layers and store.kept_frames == [11]
        monkeypatch.setattr(Decoder, "prepare_window", lambda *args: [])
        plain = model.decode_window(*args)  # each layer projects the whole memory
    for tables in (throwaway, kept):
        torch.testing.assert_close(tables.positions, plain.positions, atol=1e-6, rtol=0)
        torch.testing.assert_close(tables.visibility_logits, plain.visibility_logits)
    monkeypatch.undo()
    flat = memory.flatten(0, 1)
    standard = taptr.build_model(get_config("tiny").replace(cross_attention="standard"))
    # no store under autograd, for the grid_sample kernel, or without key-aware attention
    for decoder, execution, grad in (
        (model.decoder, "fast", True),
        (model.decoder, "reference", False),
        (standard.decoder, "fast", False),
        (model.decoder, _fast(shared_tables=False), False),
    ):
        with torch.set_grad_enabled(grad):
            prepared = decoder.prepare_window(
                content, flat, features.spatial_shapes, get_execution(execution), store
            )
        assert prepared == []
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):  # products in bfloat16
        assert model.decoder.prepare_window(content, flat, features.spatial_shapes, _fast()) == []
    with torch.no_grad(), monkeypatch.context() as patch:  # inside torch.compile
        patch.setattr(torch.compiler, "is_compiling", lambda: True)
        assert model.decoder.prepare_window(content, flat, features.spatial_shapes, _fast()) == []
    with torch.no_grad():
        assert model.decoder.prepare_window(
            content, flat, features.spatial_shapes, _fast(), store
        ) == [store]
        store.start_window(10, 12, keep_from=None)  # three frames: not this window's two
        with pytest.raises(ValueError, match="window of 3 frames; the decoder was given 2"):
            model.decode_window(*args, store)


def test_fast_execution_feeds_the_backbone_channels_last(generator):
    seen = []
    model = taptr.build_model("tiny").eval()
    model.backbone.register_forward_pre_hook(
        lambda module, inputs: seen.append(
            inputs[0].is_contiguous(memory_format=torch.channels_last)
        )
    )
    images = torch.rand(2, 3, 192, 192, generator=generator)  # CHANNELS_LAST_MIN_PIXELS
    with torch.no_grad():
        fast = model.set_execution(_fast(row_block=None)).encode_images(images).memory
        plain = model.set_execution(_fast(row_block=None, channels_last=False)).encode_images(
            images
        )
        model.set_execution(_fast(row_block=None)).encode_images(images[..., :128, :128])
    assert seen == [True, False, False]  # small frames as they are: it does not pay there
    # another convolution algorithm: float rounding, relative to the features' scale
    scale = float(plain.memory.abs().max())
    torch.testing.assert_close(fast, plain.memory, atol=1e-5 * scale, rtol=0)
    assert [e.channels_last for e in EXECUTIONS.values()] == [False, True, False]


@pytest.mark.parametrize("preset", ["tiny", "tiny-v3"])
def test_fast_execution_runs_under_autocast_with_blas_products(preset):
    """CUDA's autocast path, emulated on the CPU: BLAS products (no oneDNN) in bfloat16.

    The row blocks and the frame tables write products into float32 buffers with
    ``out=``, which autocast does not cover; under autocast they step aside (a GPU run of
    ``taptr bench --dtype bfloat16`` failed there with "mat1 and mat2 must have the same
    dtype").
    """
    from taptr.apps.benchmark import BenchConfig, _inputs, _track

    # more points than a row block, so that the blocked MLPs would be taken
    config = BenchConfig(preset=preset, frames=9, points=ROW_BLOCK // 2, size=(64, 64))
    model = taptr.build_model(preset, execution=_fast(onednn_linear=False)).eval()
    video, queries = _inputs(config)
    with torch.no_grad():
        exact = _track(model, config, video, queries)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            rounded = _track(model, config, video, queries)
    assert rounded.positions.shape == exact.positions.shape
    assert torch.isfinite(rounded.positions).all()
    assert not torch.equal(rounded.positions, exact.positions)  # bfloat16 products did run


def test_row_blocks_are_for_the_cpu_only():
    from taptr.model.ops.row_blocks import use_row_blocks

    mlp = MLP(8, 16, 8, 2).requires_grad_(False)
    rows = ROW_BLOCK + 1
    assert use_row_blocks(mlp, torch.zeros(rows, 8), ROW_BLOCK)
    assert not use_row_blocks(mlp, torch.zeros(rows, 8, device="meta"), ROW_BLOCK)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert not use_row_blocks(mlp, torch.zeros(rows, 8), ROW_BLOCK)
