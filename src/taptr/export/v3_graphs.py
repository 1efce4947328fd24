"""Exporting TAPTRv3's per-frame step as three ONNX graphs and its manifest.

`export_v3(model, directory)` writes ``encoder.onnx``, ``start_points.onnx`` and
``decode_step.onnx`` (`taptr.export.v3_modules`) and ``taptr-export.json``
(`taptr.onnx.v3_manifest.V3Manifest`). Graphs take batch size one; the frame count of the
encoder, the points N and the history buffer's slots H are dynamic; the frame size, and
with it the memory tokens S, is fixed.

The model is copied first: float32 on the CPU, eval mode, `EXPORT_EXECUTION` (the
``grid_sample`` kernel, the N × N point-attention mask, the long-temporal attention by
query products, no blocks). Outputs equal the eager model's up to float rounding.
"""

from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from taptr.config import check_history_frames
from taptr.export.exporter import ONNX_OPSET, export_onnx_graph, require_onnx_exporter
from taptr.export.modules import FixedSizeEncoder, feature_shapes
from taptr.export.v3_attention import packed_model
from taptr.export.v3_modules import (
    EXPORT_EXECUTION,
    FrameStep,
    FrameStepWithoutContext,
    PointStarter,
    PointStarterWithoutContext,
)
from taptr.geometry import INVERSE_SIGMOID_EPS
from taptr.io.atomic import atomic_path
from taptr.model.taptr import IMAGENET_MEAN, IMAGENET_STD
from taptr.model.trajectory import QuerySet
from taptr.model.v3.per_frame import initial_visibility
from taptr.model.v3.taptr import TAPTRv3
from taptr.onnx.v3_manifest import SupportRule, V3Manifest
from taptr.onnx.v3_tensors import GRAPHS, graph_specs
from taptr.task.support_schemes import LOCAL_SUPPORT_BUDGET, SupportPattern


def prepare_v3(model: TAPTRv3) -> TAPTRv3:
    """A float32 CPU copy in eval mode for export; ``model`` is untouched.

    It runs `EXPORT_EXECUTION`, and its context-aware attention samples one packed image
    of the levels (`taptr.export.v3_attention`).
    """
    prepared = copy.deepcopy(model).float().cpu().eval()
    return packed_model(prepared.set_execution(EXPORT_EXECUTION))


def unwritten_logits(model: TAPTRv3) -> tuple[list[float], list[float]]:
    """The (3,) logits of a "visible" and an "occluded" frame the model does not write.

    Read from the driver's own rule (`taptr.model.v3.per_frame.initial_visibility`) on two
    points, one starting on frame 0 with a visible label, one later with an occluded one.
    """
    queries = QuerySet(
        torch.tensor([[0, 1]]), torch.full((1, 2, 2), 0.5), torch.tensor([[True, False]])
    )
    rows = initial_visibility(model, queries, 0)[0]  # (2, 3)
    return rows[0].tolist(), rows[1].tolist()


def support_rule(model: TAPTRv3) -> SupportRule:
    """The model config's support points, in the normalised units the loop adds them in."""
    config = model.config
    assert config is not None
    pattern = SupportPattern.normalised(np.float32)  # the task layer's, as the loop adds them
    return SupportRule(
        scheme=config.support_points,
        local_budget=LOCAL_SUPPORT_BUDGET,
        local_offsets=tuple((float(x), float(y)) for x, y in pattern.local_offsets),
        grid_positions=tuple((float(x), float(y)) for x, y in pattern.grid_positions),
        grid_start_frames=tuple(int(f) for f in pattern.grid_start_frames),
        context_points=config.context_points,
    )


def v3_manifest(
    model: TAPTRv3, input_size: tuple[int, int] | None, history_frames: int | None
) -> V3Manifest:
    """The manifest of ``model``'s export at ``input_size`` (default: the config's).

    Raises:
        ValueError: a model without a config, or a history limit of 1 or below 0.
    """
    config = model.config
    if config is None:
        raise ValueError("the model has no config; build or load it with taptr")
    limit = model.history_frames if history_frames is None else history_frames
    check_history_frames(limit)
    height, width = config.input_size if input_size is None else input_size
    size = (int(height), int(width))
    shapes = tuple(feature_shapes(model, size))
    tokens = sum(h * w for h, w in shapes)
    visible, occluded = unwritten_logits(model)
    return V3Manifest(
        format="onnx",
        opset=ONNX_OPSET,
        input_size=size,
        resize=config.resize,
        mean=IMAGENET_MEAN,
        std=IMAGENET_STD,
        spatial_shapes=shapes,
        d_model=model.content_channels,
        context_patch=model.context_patch,
        num_layers=model.num_layers,
        visibility_threshold=config.visibility_threshold,
        visibility_weights=model.visibility_weights,
        visible_logits=(visible[0], visible[1], visible[2]),
        occluded_logits=(occluded[0], occluded[1], occluded[2]),
        position_eps=INVERSE_SIGMOID_EPS,
        history_frames=limit,
        support=support_rule(model),
        graphs=graph_specs(tokens, model.content_channels, model.context_patch, size),
    )


def v3_wrappers(model: TAPTRv3, manifest: V3Manifest) -> dict[str, nn.Module]:
    """The three wrapped pieces of a prepared model, by graph name."""
    shapes = [(h, w) for h, w in manifest.spatial_shapes]
    with_context = manifest.context_patch > 0
    modules: dict[str, nn.Module] = {
        "encoder": FixedSizeEncoder(model, shapes),
        "start_points": (PointStarter if with_context else PointStarterWithoutContext)(
            model, shapes
        ),
        "decode_step": (FrameStep if with_context else FrameStepWithoutContext)(model, shapes),
    }
    return {name: module.eval() for name, module in modules.items()}


def example_inputs(manifest: V3Manifest, seed: int = 0) -> dict[str, tuple[Tensor, ...]]:
    """Inputs to trace each graph with: 2 frames, 3 points, a buffer of 8 slots.

    Sizes differ from each other and from one, so that no dynamic size is mistaken for a
    constant or for another; the points start before, on and after the frame.
    """
    generator = torch.Generator().manual_seed(seed)
    points, slots, frame = 3, 8, 5
    tokens, channels, patch = manifest.num_tokens, manifest.d_model, manifest.context_patch

    def rand(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=generator)

    memory = rand(tokens, channels)
    context = (rand(points, patch, patch, channels),) if patch else ()
    slot_frames = torch.arange(frame - 6, frame + 2)  # (8,): the last one holds no frame yet
    return {
        "encoder": (rand(2, 3, *manifest.input_size),),
        "start_points": (memory, rand(points, 2)),
        "decode_step": (
            memory,
            torch.tensor(frame),
            torch.tensor([0, frame, frame + 3]),
            rand(points, channels),
            *context,
            torch.randn(points, 4, generator=generator),
            torch.randn(points, 3, generator=generator),
            rand(points, slots, channels),
            torch.randn(points, slots, generator=generator),
            slot_frames,
            slot_frames <= frame,
        ),
    }


def dynamic_shapes(manifest: V3Manifest, name: str) -> tuple[dict[int, Any] | None, ...]:
    """``torch.export`` dimensions of graph ``name``'s inputs, from the manifest's names."""
    dims = {label: torch.export.Dim(label, min=1) for label in ("frames", "points", "slots")}
    return tuple(
        {axis: dims[size] for axis, size in enumerate(spec.shape) if isinstance(size, str)} or None
        for spec in manifest.graphs[name]["inputs"]
    )


def export_v3(
    model: TAPTRv3,
    directory: str | os.PathLike[str],
    input_size: tuple[int, int] | None = None,
    history_frames: int | None = None,
) -> V3Manifest:
    """Writes TAPTRv3's three graphs as ONNX and the manifest.

    Args:
        model: the network (not modified).
        directory: output folder, created if needed.
        input_size: (H, W) of the frames the graphs take (default: the model config's).
        history_frames: the manifest's history limit (default: the model's; 0: every frame).

    Raises:
        ModuleNotFoundError: onnx or onnxscript is missing.
        ValueError: see `v3_manifest`.
    """
    require_onnx_exporter()
    prepared = prepare_v3(model)
    manifest = v3_manifest(prepared, input_size, history_frames)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    examples = example_inputs(manifest)
    for name, module in v3_wrappers(prepared, manifest).items():
        names = (manifest.input_names(name), manifest.output_names(name))
        # written beside its name, then renamed over it: never through a link there
        with atomic_path(manifest.graph_path(directory, name)) as path:
            export_onnx_graph(module, examples[name], path, names, dynamic_shapes(manifest, name))
    manifest.save(directory)
    return manifest


__all__ = ["GRAPHS", "export_v3", "prepare_v3", "v3_manifest", "v3_wrappers"]
