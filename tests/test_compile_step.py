"""TAPTRv3's per-frame decoder step compiles as one graph and computes the same.

A step that breaks its graph (a host sync, a Python branch on a tensor value, an
unsupported call) cannot be captured or compiled whole. ``fullgraph=True`` fails on any
break; the ``eager`` backend traces without generating code, so the check takes seconds.
Inductor's code generation (about 100 s for the tiny model on 2 cores) runs in the slow
suite.
"""

import copy

import pytest
import torch

from taptr.model.build import build_model
from taptr.model.taptr import normalize_frames
from taptr.model.trajectory import QuerySet
from taptr.model.v3 import per_frame
from taptr.runtime.frames import EncodedFrames


def _step_inputs(model, frames: int = 4):
    """The arguments of the decoder on frame ``frames - 1`` of a static-shape run."""
    torch.manual_seed(1)
    video = torch.rand(1, frames, 3, 64, 64)
    queries = QuerySet(
        torch.tensor([[0, 0, 1, 2, 0, 1]]), torch.rand(1, 6, 2), torch.ones(1, 6, dtype=torch.bool)
    )
    calls = []
    hook = model.decoder.register_forward_pre_hook(lambda _, args: calls.append(args))
    with torch.no_grad():
        source = EncodedFrames(model, lambda a, b: normalize_frames(video[:, a : b + 1]), 1)
        per_frame.run_frames(model, queries, frames, source, torch.float32, static_shapes=True)
    hook.remove()
    return calls


@pytest.mark.parametrize("backend", ["eager", pytest.param("inductor", marks=pytest.mark.slow)])
def test_taptrv3_decoder_step_compiles_as_one_graph(backend):
    torch.manual_seed(0)
    model = build_model("tiny-v3").eval()
    calls = _step_inputs(model)
    assert len(calls) >= 2  # frames with some points still to start, then all tracked
    torch._dynamo.reset()
    compiled = torch.compile(copy.deepcopy(model.decoder), fullgraph=True, backend=backend)
    with torch.no_grad():
        for args in calls:
            expected, got = model.decoder(*args), compiled(*args)
            torch.testing.assert_close(got.positions, expected.positions, atol=1e-5, rtol=0)
            torch.testing.assert_close(
                got.visibility_logits, expected.visibility_logits, atol=1e-5, rtol=0
            )


def test_a_compiled_decoder_gets_the_static_step():
    """A TAPTRv3 whose decoder was compiled reads the whole history buffer, as it must."""
    from taptr.runtime.compile import compile_model

    model = compile_model(build_model("tiny-v3").eval(), backend="eager")
    queries = QuerySet(
        torch.zeros(1, 2, dtype=torch.long), torch.rand(1, 2, 2), torch.ones(1, 2, dtype=torch.bool)
    )
    assert per_frame.start_state(model, queries, torch.float32).step.static_shapes
    plain = build_model("tiny-v3").eval()
    assert not per_frame.start_state(plain, queries, torch.float32).step.static_shapes
