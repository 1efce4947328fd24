"""Values projected after sampling equal the value table's samples; patch corners stay exact."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from taptr.model.ops import dense
from taptr.model.ops.context_patches import gather_context_attn, key_table, patch_corners
from taptr.model.ops.gather import bilinear_corners, gather_sum, projected_table
from taptr.model.ops.memory_values import (
    MemoryValues,
    sample_memory_values,
    values_after_sampling,
)

SHAPES = [(6, 8), (3, 4), (2, 2), (1, 1)]
"""Four levels, the last a single pixel (whose patch steps are whole levels)."""


def _case(batch: int, queries: int, seed: int = 0):
    """Memory (B, S, 16), projections with nonzero biases, locations near and past borders."""
    generator = torch.Generator().manual_seed(seed)
    tokens = sum(h * w for h, w in SHAPES)
    memory = torch.randn(batch, tokens, 16, generator=generator)
    key_proj, value_proj = torch.nn.Linear(16, 16), torch.nn.Linear(16, 16)
    with torch.no_grad():
        value_proj.bias.normal_(generator=generator)
        key_proj.bias.normal_(generator=generator)
    # (B, Q, M, L, P, 2) over [−0.3, 1.3]: inside, on and beyond every border
    locations = torch.rand(batch, queries, 2, len(SHAPES), 3, 2, generator=generator)
    return memory, key_proj, value_proj, locations * 1.6 - 0.3


@pytest.mark.parametrize("batch", [1, 2])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_sampled_memory_values_equal_the_value_tables_samples(batch, dtype):
    memory, _, value_proj, locations = _case(batch, 7)
    heads = locations.shape[2]
    rows, weights = bilinear_corners(locations, SHAPES, border=False)  # (B, Q, M, L·P, 4)
    weights = weights * torch.rand(weights.shape[:-1] + (1,))  # attention folded in
    with torch.no_grad():
        table = projected_table(memory, value_proj, SHAPES, heads, border=False)
        expected = gather_sum(table, rows.flatten(-2), weights.flatten(-2))  # (B, Q, M, D)
        sampled = sample_memory_values(
            MemoryValues(memory.to(dtype), value_proj), rows.flatten(-2), weights.flatten(-2), heads
        )
    assert sampled.shape == expected.shape
    tolerance = {} if dtype == torch.float32 else {"rtol": 0.03, "atol": 0.03}
    torch.testing.assert_close(sampled.float(), expected, **tolerance)


def test_sampled_values_have_the_tables_gradients():
    memory, _, value_proj, locations = _case(1, 3)
    rows, weights = bilinear_corners(locations, SHAPES, border=False)
    grads = []
    for sampled in (True, False):
        source = memory.clone().requires_grad_(True)
        value_proj.zero_grad()
        if sampled:
            out = sample_memory_values(
                MemoryValues(source, value_proj), rows.flatten(-2), weights.flatten(-2), 2
            )
        else:
            table = projected_table(source, value_proj, SHAPES, 2, border=False)
            out = gather_sum(table, rows.flatten(-2), weights.flatten(-2))
        out.square().sum().backward()
        grads.append((source.grad, value_proj.weight.grad.clone(), value_proj.bias.grad.clone()))
    for got, expected in zip(*grads, strict=True):
        torch.testing.assert_close(got, expected)


def _context_attn(memory, key_proj, value_proj, locations, sampled_values: bool):
    """`gather_context_attn` with the value table or the memory's values, a fixed score."""
    batch, queries, heads = locations.shape[:3]
    generator = torch.Generator().manual_seed(3)
    own = torch.randn(batch, queries, heads, 9, 8, generator=generator)
    score = torch.randn(81, generator=generator) / 9
    keys = key_table("gather", memory, key_proj, SHAPES, heads, onednn=True)
    if sampled_values:
        values = MemoryValues(memory, value_proj)
    else:
        values = projected_table(
            memory, value_proj, SHAPES, heads, border=False, onednn=True, bfloat16_rows=False
        )
    return gather_context_attn(
        keys, values, own, SHAPES, locations, lambda p: p.to(score.dtype) @ score, block=200
    )


@pytest.mark.parametrize("batch", [1, 2])
def test_context_attention_with_sampled_values_equals_the_table(batch):
    memory, key_proj, value_proj, locations = _case(batch, 9, seed=batch)
    with torch.no_grad():
        table_out, table_logits = _context_attn(memory, key_proj, value_proj, locations, False)
        out, logits = _context_attn(memory, key_proj, value_proj, locations, True)
    torch.testing.assert_close(logits, table_logits)
    torch.testing.assert_close(out, table_out)


@pytest.mark.cpu
def test_context_attention_with_sampled_values_in_bfloat16_products():
    """Inside the CPU's bfloat16 products the keys are bfloat16 rows; the sampled values are
    projected in float32 (the table is a bfloat16 product), both near the float32 run."""
    if not dense.native_bfloat16():
        pytest.skip("this CPU has no native bfloat16 products")
    memory, key_proj, value_proj, locations = _case(2, 9)
    with torch.no_grad():
        exact_out, exact_logits = _context_attn(memory, key_proj, value_proj, locations, False)
        with dense.bfloat16_products():
            table = _context_attn(memory, key_proj, value_proj, locations, False)
            sampled = _context_attn(memory, key_proj, value_proj, locations, True)
    assert sampled[0].dtype == torch.float32
    torch.testing.assert_close(sampled[1], table[1])  # the same bfloat16 key rows
    for out, logits in (table, sampled):
        torch.testing.assert_close(logits, exact_logits, rtol=0.05, atol=0.05)
        torch.testing.assert_close(out, exact_out, rtol=0.05, atol=0.05)


def test_the_decoder_step_with_sampled_values_equals_the_tables(monkeypatch):
    """The whole TAPTRv3 step: values after sampling forced on, against the tables."""
    from taptr.model.build import build_model
    from taptr.model.taptr import normalize_frames
    from taptr.model.trajectory import QuerySet
    from taptr.model.v3 import context_attention
    from taptr.model.v3.per_frame import run_frames
    from taptr.runtime.frames import PrecomputedFrames

    monkeypatch.setattr(context_attention, "values_after_sampling", lambda *_: True)
    torch.manual_seed(0)
    model = build_model("tiny-v3").eval()
    generator = torch.Generator().manual_seed(0)
    video = torch.rand(2, 4, 3, 48, 64, generator=generator)
    queries = QuerySet(
        torch.tensor([[0, 0, 1, 2, 0], [1, 0, 0, 3, 0]]),
        torch.rand(2, 5, 2, generator=generator) * 1.2 - 0.1,  # some outside the frame
        torch.ones(2, 5, dtype=torch.bool),
    )
    with torch.no_grad():
        frames = PrecomputedFrames(model.encode(normalize_frames(video)))
        outputs = []
        for on in (False, True):
            model.set_execution(dataclasses.replace(model.execution, values_after_sampling=on))
            outputs.append(run_frames(model, queries, 4, frames, torch.float32))
    torch.testing.assert_close(outputs[1].positions, outputs[0].positions, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(
        outputs[1].visibility_logits, outputs[0].visibility_logits, rtol=1e-4, atol=1e-4
    )


def test_values_are_sampled_only_where_that_costs_less():
    # TAPTRv3-R18 at 384 × 512: 16,320 tokens, 8 heads of 4 levels × 4 points
    assert values_after_sampling(136, 16, 16_320, 256, 8)
    assert values_after_sampling(836, 16, 16_320, 256, 8)
    assert not values_after_sampling(5_000, 16, 16_320, 256, 8)
    assert not values_after_sampling(136, 16, 60, 256, 8)  # a tiny frame: the table


def test_patch_corners_are_the_bilinear_corners_of_the_patch_points():
    from taptr.model.ops.context_patches import patch_locations

    _, _, _, locations = _case(2, 5)
    rows, weights = patch_corners(locations, SHAPES, 3)
    patches = patch_locations(locations, SHAPES, 3)  # (B, Q, M, L, P·9, 2)
    expected_rows, expected_weights = bilinear_corners(patches, SHAPES, border=False)
    torch.testing.assert_close(weights, expected_weights, rtol=1e-6, atol=1e-6)
    # a corner of weight zero may read any row of its level
    inside = expected_weights != 0
    assert torch.equal(rows[inside], expected_rows.to(rows.dtype)[inside])
