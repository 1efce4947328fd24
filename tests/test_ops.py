"""The pure-PyTorch multi-scale deformable sampling: hand-computed values and gradients."""

from __future__ import annotations

import pytest
import torch

from taptr.model.ops import (
    deform_attn,
    gather_deform_attn,
    gather_key_aware_attn,
    key_aware_ms_deform_attn,
    ms_deform_attn,
    padded_table,
    projected_table,
    sample_each_level,
    value_table,
)
from taptr.model.ops.gather import bilinear_corners


def _bilinear_zero_padded(image: torch.Tensor, x: float, y: float) -> torch.Tensor:
    """Reference: image (D, H, W) at pixel (x, y) = location · size − 0.5, zeros outside."""
    channels, height, width = image.shape
    x0, y0 = int(torch.floor(torch.tensor(x))), int(torch.floor(torch.tensor(y)))
    total = torch.zeros(channels, dtype=image.dtype)
    for dx in (0, 1):
        for dy in (0, 1):
            xi, yi = x0 + dx, y0 + dy
            weight = (1 - abs(x - xi)) * (1 - abs(y - yi))
            if 0 <= xi < width and 0 <= yi < height:
                total += weight * image[:, yi, xi]
    return total


def test_sampling_matches_hand_bilinear(generator):
    shapes = [(3, 4), (2, 2)]
    heads, channels = 2, 3
    values = torch.randn(
        1, 3 * 4 + 2 * 2, heads, channels, generator=generator, dtype=torch.float64
    )
    locations = (
        torch.tensor(
            [[0.5, 0.5], [0.0, 0.0], [0.99, 0.2], [1.2, 0.5], [-0.1, -0.1], [0.3, 0.9]],
            dtype=torch.float64,
        )
        .view(1, 1, 1, 1, 6, 2)
        .expand(1, 1, heads, 2, 6, 2)
    )
    sampled = list(sample_each_level(values, shapes, locations))  # (B·M, D, Q, P) per level
    starts = [0, 12]
    for head in range(heads):
        for level, (h, w) in enumerate(shapes):
            image = values[0, starts[level] : starts[level] + h * w, head].T.reshape(channels, h, w)
            for point in range(6):
                lx, ly = locations[0, 0, head, level, point].tolist()
                expected = _bilinear_zero_padded(image, lx * w - 0.5, ly * h - 0.5)
                got = sampled[level][head, :, 0, point]
                torch.testing.assert_close(got, expected)


def test_centre_of_a_cell_reads_the_cell_exactly():
    values = torch.arange(6, dtype=torch.float64).view(1, 6, 1, 1)  # one level 2×3, one channel
    location = torch.tensor([(1.5 / 3), (0.5 / 2)], dtype=torch.float64).view(1, 1, 1, 1, 1, 2)
    out = ms_deform_attn(values, [(2, 3)], location, torch.ones(1, 1, 1, 1, 1, dtype=torch.float64))
    assert out.item() == 1.0  # row 0, column 1


def test_standard_attention_gradcheck(generator):
    shapes = [(3, 3), (2, 2)]
    values = torch.randn(1, 13, 2, 2, dtype=torch.float64, generator=generator, requires_grad=True)
    locations = torch.rand(1, 3, 2, 2, 2, 2, dtype=torch.float64, generator=generator) * 0.8 + 0.1
    locations.requires_grad_(True)
    weights = torch.rand(1, 3, 2, 2, 2, dtype=torch.float64, generator=generator).softmax(-1)
    weights.requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda v, loc, w: ms_deform_attn(v, shapes, loc, w), (values, locations, weights)
    )


def test_key_aware_attention_gradcheck(generator):
    shapes = [(3, 3), (2, 2)]
    q = torch.randn(1, 3, 2, 2, dtype=torch.float64, generator=generator, requires_grad=True)
    k = torch.randn(1, 13, 2, 2, dtype=torch.float64, generator=generator, requires_grad=True)
    v = torch.randn(1, 13, 2, 2, dtype=torch.float64, generator=generator, requires_grad=True)
    locations = torch.rand(1, 3, 2, 2, 2, 2, dtype=torch.float64, generator=generator) * 0.8 + 0.1
    locations.requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda *args: key_aware_ms_deform_attn(args[0], args[1], args[2], shapes, args[3]),
        (q, k, v, locations),
    )


def test_key_aware_weights_are_softmaxed_scaled_dot_products(generator):
    shapes = [(2, 2)]
    channels = 4
    q = torch.randn(1, 1, 1, channels, dtype=torch.float64, generator=generator)
    k = torch.randn(1, 4, 1, channels, dtype=torch.float64, generator=generator)
    v = torch.randn(1, 4, 1, channels, dtype=torch.float64, generator=generator)
    # the four cell centres of the 2×2 map, as four sampling points of one level
    centres = torch.tensor(
        [[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]], dtype=torch.float64
    )
    locations = centres.view(1, 1, 1, 1, 4, 2)
    out, logits = key_aware_ms_deform_attn(q, k, v, shapes, locations)
    expected_logits = (k[0, :, 0] @ q[0, 0, 0]) / channels**0.5
    torch.testing.assert_close(logits.flatten(), expected_logits)
    expected = expected_logits.softmax(0) @ v[0, :, 0]
    torch.testing.assert_close(out.flatten(), expected)


def _random_case(generator, batch=2, queries=5, heads=2, channels=3, points=3):
    shapes = [(5, 7), (3, 4), (1, 2)]
    tokens = sum(h * w for h, w in shapes)
    values = torch.randn(batch, tokens, heads, channels, dtype=torch.float64, generator=generator)
    # some locations outside [0, 1] exercise the zero padding
    locations = torch.rand(
        batch, queries, heads, 3, points, 2, dtype=torch.float64, generator=generator
    )
    locations = locations * 1.4 - 0.2
    return shapes, values, locations


def test_gather_kernel_equals_grid_sample(generator):
    shapes, values, locations = _random_case(generator)
    weights = torch.rand(*locations.shape[:-1], dtype=torch.float64, generator=generator)
    weights = weights.flatten(-2).softmax(-1).view_as(weights)
    reference = ms_deform_attn(values, shapes, locations, weights)
    torch.testing.assert_close(
        gather_deform_attn(padded_table(values, shapes), shapes, locations, weights), reference
    )

    queries = torch.randn(2, 5, 2, 3, dtype=torch.float64, generator=generator)
    keys = torch.randn_like(values)
    ref_out, ref_logits = key_aware_ms_deform_attn(queries, keys, values, shapes, locations)
    out, logits = gather_key_aware_attn(
        queries, padded_table(keys, shapes), padded_table(values, shapes), shapes, locations
    )
    torch.testing.assert_close(out, ref_out)
    torch.testing.assert_close(logits, ref_logits)


def test_gather_kernels_gradcheck(generator):
    shapes, values, locations = _random_case(generator, batch=1, queries=2, points=2)
    values.requires_grad_(True)
    locations = (locations * 0.6 + 0.2).requires_grad_(True)  # away from cell borders' kinks
    weights = torch.rand(*locations.shape[:-1], dtype=torch.float64, generator=generator)
    weights.requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda v, loc, w: gather_deform_attn(padded_table(v, shapes), shapes, loc, w),
        (values, locations, weights),
    )
    queries = torch.randn(1, 2, 2, 3, dtype=torch.float64, generator=generator, requires_grad=True)
    keys = torch.randn_like(values, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda *a: gather_key_aware_attn(
            a[0], padded_table(a[1], shapes), padded_table(a[2], shapes), shapes, a[3]
        ),
        (queries, keys, values, locations),
    )


@pytest.mark.parametrize(
    ("execution", "kernel"),
    [("fast", "gather"), ("reference", "grid_sample"), ("training", "grid_sample")],
)
def test_the_execution_picks_every_attention_kernel(monkeypatch, execution, kernel):
    import taptr.model.attention as attention
    from taptr import build_model

    used = []

    def spy(function):
        def wrapped(kernel, *args, **kwargs):
            used.append(kernel)
            return function(kernel, *args, **kwargs)

        return wrapped

    monkeypatch.setattr(attention, "deform_attn", spy(attention.deform_attn))
    monkeypatch.setattr(attention, "key_aware_attn", spy(attention.key_aware_attn))
    model = build_model("tiny", execution=execution).eval()
    assert model.execution.kernel == kernel
    assert not any(hasattr(m, "kernel") for m in model.modules())  # no per-module mode
    with torch.no_grad():
        features = model.encode_images(torch.zeros(1, 3, 64, 64))
        tracking = torch.ones(1, 1, 2, dtype=torch.bool)
        model.decode_window(
            features.memory[:, None],
            features.spatial_shapes,
            torch.zeros(1, 1, 2, 32),
            torch.zeros(1, 1, 2, 4),
            tracking,
            tracking,
        )
    layers = len(model.encoder.layers) + len(model.decoder.layers)
    assert used == [kernel] * layers


def test_gather_kernel_at_and_beyond_the_far_border():
    """Locations clamped onto the last level's far border must stay inside the table."""
    shapes = [(2, 3), (1, 2)]
    values = torch.randn(1, 8, 1, 2, dtype=torch.float64)
    edge = torch.tensor(
        [[1.0, 1.0], [5.0, 5.0], [-3.0, 0.5], [1.0 + 0.5 / 3, 0.5]], dtype=torch.float64
    )
    locations = edge.view(1, 4, 1, 1, 1, 2).expand(1, 4, 1, 2, 1, 2).contiguous()
    weights = torch.full((1, 4, 1, 2, 1), 0.5, dtype=torch.float64)
    reference = ms_deform_attn(values, shapes, locations, weights)
    torch.testing.assert_close(
        gather_deform_attn(padded_table(values, shapes), shapes, locations, weights), reference
    )


def test_key_aware_chunking_is_exact(generator, monkeypatch):
    import taptr.model.ops.gather as gather

    shapes, values, locations = _random_case(generator, queries=7)
    queries = torch.randn(2, 7, 2, 3, dtype=torch.float64, generator=generator)
    keys = torch.randn_like(values)
    whole = gather_key_aware_attn(
        queries, padded_table(keys, shapes), padded_table(values, shapes), shapes, locations
    )
    monkeypatch.setattr(gather, "CHUNK_ELEMENTS", 2 * 2 * 3 * 3 * 3 * 2)  # two queries a chunk
    chunked = gather_key_aware_attn(
        queries, padded_table(keys, shapes), padded_table(values, shapes), shapes, locations
    )
    torch.testing.assert_close(chunked[0], whole[0])
    torch.testing.assert_close(chunked[1], whole[1])


def test_projected_table_equals_padding_the_projection(generator):
    shapes = [(3, 4), (2, 2)]
    memory = torch.randn(2, 16, 8, generator=generator)
    projection = torch.nn.Linear(8, 8)
    with torch.no_grad():
        fast = projected_table(memory, projection, shapes, heads=2)
        plain = padded_table(projection(memory).view(2, 16, 2, 4), shapes)
    torch.testing.assert_close(fast, plain)
    with torch.enable_grad():  # the differentiable formulation is used when gradients are needed
        table = projected_table(memory, projection, shapes, heads=2)
        assert table.requires_grad
        torch.testing.assert_close(table, plain)


def test_deform_attn_kernels_agree(generator):
    shapes = [(3, 4), (2, 2)]
    memory = torch.randn(2, 16, 8, generator=generator, dtype=torch.float64)
    projection = torch.nn.Linear(8, 8).double()
    locations = torch.rand(2, 3, 2, 2, 2, 2, generator=generator, dtype=torch.float64)
    weights = torch.rand(2, 3, 2, 2, 2, generator=generator, dtype=torch.float64)
    with torch.no_grad():
        outputs = [
            deform_attn(
                kernel,
                value_table(kernel, memory, projection, shapes, heads=2),
                shapes,
                locations,
                weights,
            )
            for kernel in ("grid_sample", "gather")
        ]
    torch.testing.assert_close(outputs[0], outputs[1])


def test_key_aware_attn_on_tables_made_per_image_equals_the_memory(generator):
    from taptr.model.ops import key_aware_attn

    shapes, _, locations = _random_case(generator, heads=2, channels=4)
    tokens = sum(h * w for h, w in shapes)
    memory = torch.randn(2, tokens, 8, dtype=torch.float64, generator=generator)
    key_proj = torch.nn.Linear(8, 8).double()
    value_proj = torch.nn.Linear(8, 8).double()
    queries = torch.randn(2, 5, 2, 4, dtype=torch.float64, generator=generator)
    args = (queries, memory, key_proj, value_proj, shapes, locations)
    with torch.no_grad():
        reference = key_aware_attn("grid_sample", *args)
        tables = ((key_proj(image), value_proj(image)) for image in memory)  # (S, C) each
        per_image = key_aware_attn("gather", *args, tables)
        whole = key_aware_attn("gather", *args)
    for mine, theirs in ((per_image, reference), (whole, reference)):
        torch.testing.assert_close(mine[0], theirs[0])
        torch.testing.assert_close(mine[1], theirs[1])
    # given tables, the memory is not read
    with torch.no_grad():
        tables = [(key_proj(image), value_proj(image)) for image in memory]
        unread = key_aware_attn("gather", queries, memory.mul(float("nan")), *args[2:], tables)
    torch.testing.assert_close(unread[0], per_image[0], atol=0, rtol=0)


def _table(values: torch.Tensor, shapes, border: bool) -> torch.Tensor:
    """(B, S, M, D) values as gather rows, with or without the zero border."""
    return padded_table(values, shapes) if border else values.reshape(-1, values.shape[-1])


def test_key_aware_without_the_border_equals_grid_sample(generator):
    shapes, values, locations = _random_case(generator)
    # and the far-border cases of the test above, on every level
    edge = torch.tensor([[1.0, 1.0], [5.0, 5.0], [-3.0, 0.5], [1.0 + 0.5 / 3, 0.5]])
    locations[:, :4] = edge.to(locations).view(1, 4, 1, 1, 1, 2)
    queries = torch.randn(2, 5, 2, 3, dtype=torch.float64, generator=generator)
    keys = torch.randn_like(values)
    reference = key_aware_ms_deform_attn(queries, keys, values, shapes, locations)
    for border in (True, False):
        out, logits = gather_key_aware_attn(
            queries,
            _table(keys, shapes, border),
            _table(values, shapes, border),
            shapes,
            locations,
            border=border,
        )
        torch.testing.assert_close(out, reference[0])
        torch.testing.assert_close(logits, reference[1])


def test_borderless_corners_weigh_outside_corners_zero():
    shapes = [(3, 4)]
    # x = 0.1·4 − 0.5 = −0.1: only the right column is inside;
    # y = 0.9·3 − 0.5 = 2.2: only the top row
    rows, weights = bilinear_corners(
        torch.tensor([0.1, 0.9], dtype=torch.float64).view(1, 1, 1, 1, 1, 2), shapes, border=False
    )
    assert rows.flatten().tolist() == [8, 8, 8, 8]  # every corner clamped onto (y 2, x 0)
    torch.testing.assert_close(
        weights.flatten(), torch.tensor([0.0, 0.8 * 0.9, 0.0, 0.0], dtype=torch.float64)
    )


def test_projected_table_without_the_border_is_the_projection(generator):
    shapes = [(3, 4), (2, 2)]
    memory = torch.randn(2, 16, 8, generator=generator)
    projection = torch.nn.Linear(8, 8)
    plain = projection(memory).detach().reshape(-1, 4)
    with torch.no_grad():
        torch.testing.assert_close(
            projected_table(memory, projection, shapes, 2, border=False), plain
        )
    table = projected_table(memory, projection, shapes, 2, border=False)
    assert table.requires_grad
    torch.testing.assert_close(table, plain)
