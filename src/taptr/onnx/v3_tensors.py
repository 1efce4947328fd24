"""The tensors of TAPTRv3's three exported graphs: names, types and symbolic shapes.

What every engine feeds each graph and reads back (`taptr.onnx.graph_engines`), what the
exporter names them (`taptr.export.v3_graphs`) and what a manifest must describe
(`taptr.onnx.v3_manifest` compares the ``graphs`` it reads with `graph_specs`).
"""

from __future__ import annotations

from dataclasses import dataclass

GRAPHS = ("encoder", "start_points", "decode_step")
"""Graph names: frames → memory; memory and positions → content and context; one frame's
decoder with its state."""

FILES = {name: f"{name}.onnx" for name in GRAPHS}


@dataclass(frozen=True)
class TensorSpec:
    """One input or output of a graph.

    Attributes:
        name: its name in the graph.
        dtype: ``float32``, ``int64`` or ``bool``.
        shape: sizes, numbers where fixed and names where dynamic (``points`` N,
            ``slots`` H of the history buffer, ``frames`` F).
    """

    name: str
    dtype: str
    shape: tuple[int | str, ...]


def graph_specs(
    tokens: int, channels: int, patch: int, input_size: tuple[int, int]
) -> dict[str, dict[str, tuple[TensorSpec, ...]]]:
    """Each graph's inputs and outputs, in call order, for the model's sizes.

    Args:
        tokens: S, memory tokens of a frame.
        channels: C.
        patch: K, side of the points' context (0: a model without it, no context tensors).
        input_size: (H, W) of the frames.
    """
    n, h = "points", "slots"
    context = (TensorSpec("context", "float32", (n, patch, patch, channels)),) if patch else ()
    memory = TensorSpec("memory", "float32", (tokens, channels))
    return {
        "encoder": {
            "inputs": (TensorSpec("frames", "float32", ("frames", 3, *input_size)),),
            "outputs": (TensorSpec("memory", "float32", ("frames", tokens, channels)),),
        },
        "start_points": {
            "inputs": (memory, TensorSpec("positions", "float32", (n, 2))),
            "outputs": (TensorSpec("content", "float32", (n, channels)), *context),
        },
        "decode_step": {
            "inputs": (
                memory,
                TensorSpec("frame", "int64", ()),
                TensorSpec("start_frames", "int64", (n,)),
                TensorSpec("initial_content", "float32", (n, channels)),
                *context,
                TensorSpec("positions", "float32", (n, 4)),
                TensorSpec("visibility", "float32", (n, 3)),
                TensorSpec("history_content", "float32", (n, h, channels)),
                TensorSpec("history_visibility", "float32", (n, h)),
                TensorSpec("slot_frames", "int64", (h,)),
                TensorSpec("slot_held", "bool", (h,)),
            ),
            "outputs": (
                TensorSpec("new_positions", "float32", (n, 4)),
                TensorSpec("new_visibility", "float32", (n, 3)),
                TensorSpec("features", "float32", (n, channels)),
            ),
        },
    }
