"""The decoder's key and value tables made once per frame and layer, shared by windows."""

import dataclasses

import torch

import taptr
from taptr.model.execution import get_execution
from taptr.model.frame_tables import FrameTables
from taptr.model.sliding_window import run_windows
from taptr.model.taptr import normalize_frames
from taptr.model.trajectory import QuerySet
from taptr.runtime.frames import EncodedFrames


def _layer_tables(store, layer, memory, projection):
    """Consumes ``store.images`` one pair at a time, as the attention does; copies of them."""
    return [
        (keys.clone(), values.clone()) for keys, values in store.images(layer, memory, *projection)
    ]


def test_a_window_reads_the_tables_the_last_one_kept(generator):
    projection = (torch.nn.Linear(4, 4), torch.nn.Linear(4, 4))
    memory = torch.randn(4, 6, 4, generator=generator)  # frames 0..3, 6 tokens, 4 channels
    store = FrameTables()
    store.start_window(0, 3, keep_from=2)
    with torch.no_grad():
        first = _layer_tables(store, 0, memory, projection)
        expected = [(projection[0](image), projection[1](image)) for image in memory]
        for (keys, values), (want_keys, want_values) in zip(first, expected, strict=True):
            torch.testing.assert_close(keys, want_keys)
            torch.testing.assert_close(values, want_values)
        assert store.projections == 4 and store.kept_frames == [2, 3]
        # frames 0 and 1 are not kept: one pair served both in turn, then frame 2
        assert store._spare == []
        owned = {store._kept[(0, 0, frame)].data_ptr() for frame in (2, 3)}
        assert len(owned) == 2

        store.start_window(2, 5, keep_from=4)
        later = torch.cat((memory[2:].mul(float("nan")), torch.randn(2, 6, 4)))  # frames 2..5
        second = _layer_tables(store, 0, later, projection)
    # frames 2 and 3 come from the store (their memory is not read), 4 and 5 are new
    assert store.projections == 6 and store.kept_frames == [4, 5]
    for (keys, values), (old_keys, old_values) in zip(second[:2], first[2:], strict=True):
        torch.testing.assert_close(keys, old_keys, atol=0, rtol=0)
        torch.testing.assert_close(values, old_values, atol=0, rtol=0)
    # the new frames were written over released pairs, not fresh allocations
    assert {store._kept[(0, 0, frame)].data_ptr() for frame in (4, 5)} == owned
    store.start_window(6, 9, keep_from=None)
    assert store.kept_frames == []


def test_tables_are_kept_per_layer_and_per_video_of_the_batch(generator):
    projections = [(torch.nn.Linear(4, 4), torch.nn.Linear(4, 4)) for _ in range(2)]
    memory = torch.randn(2 * 3, 5, 4, generator=generator)  # B = 2 videos × W_t = 3 frames
    store = FrameTables()
    store.start_window(0, 2, keep_from=1)
    with torch.no_grad():
        for layer, projection in enumerate(projections):
            _layer_tables(store, layer, memory, projection)
        assert sorted(store._kept) == [
            (layer, video, frame) for layer in (0, 1) for video in (0, 1) for frame in (1, 2)
        ]
        store.start_window(1, 3, keep_from=None)
        # frames 1 and 2 of both videos kept for both layers: only frame 3 is new
        for layer, projection in enumerate(projections):
            tables = _layer_tables(store, layer, memory, projection)
            # video 1, frame 2: image 4 now, image 5 of the first window
            torch.testing.assert_close(tables[4][0], projection[0](memory[5]), atol=0, rtol=0)
    assert store.projections == 2 * 6 + 2 * 2


def test_tracking_projects_each_frame_once_per_layer(monkeypatch, generator):
    from taptr.model.frame_tables import FrameTables as Store

    torch.manual_seed(0)
    model = taptr.build_model("tiny").eval()
    frames = 14  # windows 0-7, 4-11 and the last one shifted back to 6-13
    video = torch.randint(0, 256, (2, frames, 3, 64, 64), generator=generator, dtype=torch.uint8)
    queries = QuerySet(
        torch.tensor([[0, 0, 5], [0, 3, 9]]),
        torch.rand(2, 3, 2, generator=generator) * 0.8 + 0.1,
        torch.ones(2, 3, dtype=torch.bool),
    )
    calls, keeps = [], []
    original, start = Store._project, Store.start_window
    monkeypatch.setattr(
        Store, "_project", lambda self, *args: calls.append(1) or original(self, *args)
    )
    monkeypatch.setattr(
        Store,
        "start_window",
        lambda self, first, last, keep_from: (
            keeps.append(keep_from) or start(self, first, last, keep_from)
        ),
    )

    def track(execution):
        model.set_execution(execution)
        source = EncodedFrames(model, lambda a, b: normalize_frames(video[:, a : b + 1] / 255))
        with torch.no_grad():
            return run_windows(model, queries, frames, source, torch.float32)

    shared = track(get_execution("fast"))
    # frames 0-7, then 8-11 (4-7 kept), then 12-13 (6-11 kept: the last window is shifted
    # back to 6-13, which the driver knows)
    assert len(calls) == (8 + 4 + 2) * model.num_layers * 2
    assert keeps == [4, 6, None]  # the last window keeps nothing
    calls.clear()
    plain = track(dataclasses.replace(get_execution("fast"), shared_tables=False))
    assert calls == []
    torch.testing.assert_close(shared.positions, plain.positions, atol=1e-6, rtol=0)
    torch.testing.assert_close(shared.visibility_logits, plain.visibility_logits, atol=1e-5, rtol=0)
