"""Exporting the per-window model step as ONNX or TorchScript graphs.

`export_model(model, directory, format)` writes the three graphs of
`taptr.export.manifest.GRAPHS` and the manifest. Graphs take batch size one; the number of
frames F (encoder), the window length W_t and the number of points N (decoder) are
dynamic; the frame size, and with it the token count S, is fixed to the model's input
size.

Before export the model is copied and prepared: float32 on the CPU, eval mode, the
``grid_sample`` attention kernel (4-D ``grid_sample`` exports to ONNX GridSample;
``embedding_bag`` with per-sample weights does not export) and the decoder's masked
point-attention path, which has no data-dependent control flow. Neither changes results
beyond float rounding.
"""

from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from taptr.export.exporter import (
    ONNX_OPSET,
    export_onnx_graph,
    quiet_exporter,
    require_onnx_exporter,
)
from taptr.export.manifest import INPUT_NAMES, OUTPUT_NAMES, ExportFormat, ExportManifest
from taptr.export.modules import FrameEncoder, PointInitializer, WindowDecoder, feature_shapes
from taptr.export.v3_graphs import export_v3
from taptr.io.atomic import atomic_path
from taptr.model.taptr import TAPTR
from taptr.model.v3.taptr import TAPTRv3
from taptr.onnx.v3_manifest import V3Manifest


class NotExportableError(ValueError):
    """The model's step does not fit the exported graphs; the message says why."""


def prepare_for_export(model: TAPTR) -> TAPTR:
    """A float32 CPU copy in eval mode with export-friendly kernels; ``model`` is untouched.

    Raises:
        NotExportableError: for a TAPTRv3 model, whose graphs differ
            (`taptr.export.v3_graphs.prepare_v3`).
    """
    if isinstance(model, TAPTRv3):
        raise NotExportableError(
            "TAPTRv3's per-frame step has graphs of its own: export it with "
            "taptr.export.export_model(model, directory, 'onnx') (taptr.export.v3_graphs)"
        )
    prepared = copy.deepcopy(model).float().cpu().eval()
    # the reference execution: the grouped point attention loops over frames with
    # data-dependent sizes (the masked formulation computes the same kept outputs in one
    # batched call), and the MLPs' row blocks would be traced as a loop of out= products
    return prepared.set_execution("reference")


def _manifest(
    model: TAPTR, format: ExportFormat, opset: int | None, input_size: tuple[int, int] | None
) -> ExportManifest:
    if model.config is None:
        raise ValueError("the model has no config; build or load it with taptr")
    config = model.config
    height, width = config.input_size if input_size is None else input_size
    size = (int(height), int(width))
    return ExportManifest(
        format=format,
        input_size=size,
        spatial_shapes=tuple(feature_shapes(model, size)),
        d_model=config.d_model,
        window_size=model.window_size,
        window_stride=model.window_stride,
        long_video_frames=model.long_video_frames,
        memory_efficient=model.memory_efficient,
        version=config.version,
        opset=opset,
    )


def _wrappers(model: TAPTR, manifest: ExportManifest) -> dict[str, nn.Module]:
    shapes = [(h, w) for h, w in manifest.spatial_shapes]
    modules: dict[str, nn.Module] = {
        "encoder": FrameEncoder(model),
        "init_points": PointInitializer(model, shapes),
        "decode_window": WindowDecoder(model, shapes),
    }
    return {name: module.eval() for name, module in modules.items()}


def example_inputs(manifest: ExportManifest, seed: int = 0) -> dict[str, tuple[Tensor, ...]]:
    """Inputs to trace each graph with: 2 frames, a window of 4 frames, 3 points.

    Sizes differ from each other and from one, so that no dynamic size is mistaken for a
    constant or for another size.
    """
    generator = torch.Generator().manual_seed(seed)
    length, points = 4, 3
    tokens, channels = manifest.num_tokens, manifest.d_model

    def rand(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=generator)

    starts = torch.tensor([0, 1, 3])  # one point per kind: tracked early, later, at the end
    window = torch.arange(length)[:, None]  # (W_t, 1)
    return {
        "encoder": (rand(2, 3, *manifest.input_size),),
        "init_points": (rand(tokens, channels), rand(points, 2)),
        "decode_window": (
            rand(length, tokens, channels),
            rand(length, points, channels),
            torch.randn(length, points, 4, generator=generator),
            rand(points, channels),
            window >= starts,
            window > starts,
        ),
    }


def _dynamic_shapes(name: str) -> tuple[dict[int, Any] | None, ...]:
    frames = torch.export.Dim("frames", min=1)
    window = torch.export.Dim("window", min=1)
    points = torch.export.Dim("points", min=1)
    per_point = {0: window, 1: points}  # (W_t, N, ...)
    return {
        "encoder": ({0: frames},),
        "init_points": (None, {0: points}),
        "decode_window": ({0: window}, per_point, per_point, {0: points}, per_point, per_point),
    }[name]


def export_onnx(
    model: TAPTR, directory: str | os.PathLike[str], input_size: tuple[int, int] | None = None
) -> ExportManifest:
    """Writes the three graphs as ONNX (torch.export-based exporter) and the manifest.

    Args:
        model: the network (not modified).
        directory: output folder, created if needed.
        input_size: (H, W) of the frames the graphs take (default: the model config's).
    """
    require_onnx_exporter()
    prepared = prepare_for_export(model)
    manifest = _manifest(prepared, "onnx", ONNX_OPSET, input_size)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    examples = example_inputs(manifest)
    for name, module in _wrappers(prepared, manifest).items():
        names = (list(INPUT_NAMES[name]), list(OUTPUT_NAMES[name]))
        # written beside its name, then renamed over it: never through a link there
        with atomic_path(manifest.graph_path(directory, name)) as path:
            export_onnx_graph(module, examples[name], path, names, _dynamic_shapes(name))
    manifest.save(directory)
    return manifest


def export_torchscript(
    model: TAPTR, directory: str | os.PathLike[str], input_size: tuple[int, int] | None = None
) -> ExportManifest:
    """Writes the three graphs as traced TorchScript modules and the manifest.

    Tracing records the operations run on the example inputs; the wrapped functions have
    no data-dependent branches once prepared, so the graphs hold for any F, W_t and N
    (checked by the tests on sizes other than the examples').

    Args:
        model: the network (not modified).
        directory: output folder, created if needed.
        input_size: (H, W) of the frames the graphs take (default: the model config's).
    """
    prepared = prepare_for_export(model)
    manifest = _manifest(prepared, "torchscript", None, input_size)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    examples = example_inputs(manifest)
    for name, module in _wrappers(prepared, manifest).items():
        with quiet_exporter(), torch.no_grad():
            traced = torch.jit.trace(module, examples[name], check_trace=False)
            with atomic_path(manifest.graph_path(directory, name)) as path:
                torch.jit.save(traced, str(path))
    manifest.save(directory)
    return manifest


def export_model(
    model: TAPTR,
    directory: str | os.PathLike[str],
    format: ExportFormat,
    input_size: tuple[int, int] | None = None,
    history_frames: int | None = None,
) -> ExportManifest | V3Manifest:
    """Exports ``model``'s per-window step, or TAPTRv3's per-frame step, in ``format``.

    TAPTRv3 goes through `taptr.export.v3_graphs.export_v3` (ONNX only).

    Args:
        model: the network (not modified).
        directory: output folder, created if needed.
        format: ``"onnx"`` or ``"torchscript"``.
        input_size: (H, W) of the frames the graphs take (default: the model config's).
        history_frames: TAPTRv3: the manifest's history limit (default: the model's).

    Raises:
        ValueError: an unknown format, ``history_frames`` for another model.
        NotExportableError: TAPTRv3 as TorchScript.
    """
    exporters = {"onnx": export_onnx, "torchscript": export_torchscript}
    if format not in exporters:
        raise ValueError(f"unknown export format {format!r}; choose onnx or torchscript")
    if isinstance(model, TAPTRv3):
        if format != "onnx":
            raise NotExportableError(
                "TAPTRv3 exports to ONNX (--format onnx), run by taptr.export.OnnxTracker"
            )
        return export_v3(model, directory, input_size, history_frames)
    if history_frames is not None:
        raise ValueError("history_frames applies to TAPTRv3 models only")
    return exporters[format](model, directory, input_size)
