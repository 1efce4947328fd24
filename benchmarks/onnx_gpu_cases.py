"""TAPTRv3's exported graphs through onnxruntime on a GPU: the cases of gpu_lean_step.py.

Per variant, the encoder and ``decode_step`` are timed per frame with their inputs and
outputs bound on the device (I/O binding), at N points and a history buffer of 32 slots
(what 24 frames hold), after one untimed run (kernel choice, CUDA graph capture, TensorRT
engine build):

- ``cuda_float32``, ``cuda_float16``: the CUDA execution provider, on the float32 graphs
  and on graphs exported in float16 (the model halved before export);
- ``cuda_graph_float32``, ``cuda_graph_float16``: the same, replayed as CUDA graphs
  (``enable_cuda_graph``; every input and output bound at a fixed address, which the
  step's static shapes per point count and buffer size allow);
- ``tensorrt_float32``, ``tensorrt_float16``: the TensorRT provider (float16 through its
  ``trt_fp16_enable``), falling back to CUDA for what it does not take.

A variant whose provider is missing, or that fails, is reported with the reason instead
of numbers. Without a GPU (the dry check) the same code times the CPU provider.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort
import torch

from taptr.export.exporter import export_onnx_graph
from taptr.export.v3_graphs import (
    dynamic_shapes,
    example_inputs,
    export_v3,
    prepare_v3,
    v3_manifest,
    v3_wrappers,
)
from taptr.onnx.ort_engine import preset_providers, session_options
from taptr.onnx.v3_manifest import V3Manifest
from taptr.onnx.v3_tensors import GRAPHS

SLOTS = 32
"""History slots of the timed step (24 frames held)."""


def export_half(model: torch.nn.Module, folder: Path) -> Path:
    """The three graphs with float16 weights and float tensors, beside a float32 manifest."""
    prepared = prepare_v3(model)
    manifest = v3_manifest(prepared, None, None)
    half = prepared.half()
    examples = example_inputs(manifest)
    folder.mkdir(parents=True, exist_ok=True)
    for name, module in v3_wrappers(half, manifest).items():
        inputs = tuple(x.half() if x.is_floating_point() else x for x in examples[name])
        names = (manifest.input_names(name), manifest.output_names(name))
        path = manifest.graph_path(folder, name)
        export_onnx_graph(module, inputs, path, names, dynamic_shapes(manifest, name))
    manifest.save(folder)
    return folder


def providers(kind: str, half: bool, cache: str) -> list[Any]:
    """onnxruntime providers of a variant kind: the engine's presets (`taptr.onnx.ort_engine`).

    ``kind``: ``cpu``, ``cuda``, ``cuda_graph`` or ``tensorrt``; TensorRT builds float16
    engines for the float16 graphs.
    """
    chosen = preset_providers(kind.replace("cuda_graph", "cuda-graphs"), cache)
    if kind == "tensorrt" and half:
        name, options = chosen[0]
        chosen[0] = (name, {**options, "trt_fp16_enable": "1"})
    return chosen


def step_feed(sessions: dict, manifest: V3Manifest, points: int, half: bool) -> dict:
    """``decode_step``'s inputs at ``points`` points: memory and contexts from the graphs."""
    dtype = np.float16 if half else np.float32
    rng = np.random.default_rng(0)
    frame = rng.random((1, 3, *manifest.input_size), dtype=np.float32).astype(dtype)
    memory = sessions["encoder"].run(None, {"frames": frame})[0][0]
    xy = rng.uniform(0.05, 0.95, (points, 2)).astype(dtype)
    started = sessions["start_points"].run(None, {"memory": memory, "positions": xy})
    content = started[0]
    feed = {
        "memory": memory,
        "frame": np.array(SLOTS - 1, np.int64),
        "start_frames": np.zeros(points, np.int64),
        "initial_content": content,
        "positions": np.zeros((points, 4), dtype),
        "visibility": np.zeros((points, 3), dtype),
        "history_content": np.repeat(content[:, None], SLOTS, axis=1),
        "history_visibility": np.zeros((points, SLOTS), dtype),
        "slot_frames": np.arange(SLOTS, dtype=np.int64),
        "slot_held": np.ones(SLOTS, bool),
    }
    if len(started) > 1:
        feed["context"] = started[1]
    return {name: feed[name] for name in manifest.input_names("decode_step")}


def bound(session: ort.InferenceSession, feed: dict, device: str) -> Any:
    """An I/O binding with every input and output at a fixed address on ``device``."""
    binding = session.io_binding()
    for name, value in feed.items():
        binding.bind_ortvalue_input(name, ort.OrtValue.ortvalue_from_numpy(value, device, 0))
    for output in session.get_outputs():
        binding.bind_output(output.name, device)
    session.run_with_iobinding(binding)  # allocates the outputs (and captures a CUDA graph)
    for output, value in zip(session.get_outputs(), binding.get_outputs(), strict=True):
        binding.bind_ortvalue_output(output.name, value)
    return binding


def seconds_per_run(session: ort.InferenceSession, binding: Any, runs: int) -> float:
    """Best seconds of one bound run (the runs end synchronised on the device)."""
    best = float("inf")
    for _ in range(runs):
        start = time.perf_counter()
        session.run_with_iobinding(binding)
        best = min(best, time.perf_counter() - start)
    return best


def one_variant(
    folder: str, kind: str, half: bool, points: int, runs: int, cache: Path
) -> dict[str, float]:
    """Encoder and decode_step of one variant: seconds and frames per second.

    ``cache``: where TensorRT keeps the engines it builds.
    """
    manifest = V3Manifest.load(folder)
    chosen = providers(kind, half, str(cache))
    options = session_options(None)
    sessions = {
        name: ort.InferenceSession(
            str(manifest.graph_path(folder, name)), options, providers=chosen
        )
        for name in GRAPHS
    }
    device = "cpu" if kind == "cpu" else "cuda"
    feed = step_feed(sessions, manifest, points, half)
    frame = {"frames": np.zeros((1, 3, *manifest.input_size), feed["memory"].dtype)}
    step = seconds_per_run(
        sessions["decode_step"], bound(sessions["decode_step"], feed, device), runs
    )
    encode = seconds_per_run(sessions["encoder"], bound(sessions["encoder"], frame, device), runs)
    return {
        "decode_step_s": step,
        "encoder_s": encode,
        "decode_step_fps": 1 / step,
        "frame_fps": 1 / (step + encode),
    }


def variants(available: list[str]) -> list[tuple[str, str]]:
    """(provider kind, dtype) pairs to time: the GPU's six, or the CPU's float32 alone."""
    if "CUDAExecutionProvider" not in available:
        return [("cpu", "float32")]  # the CPU provider lacks float16 kernels for these graphs
    return [(k, d) for k in ("cuda", "cuda_graph", "tensorrt") for d in ("float32", "float16")]


def onnx_cases(
    model: torch.nn.Module, points: int, runs: int, float32: str | None = None
) -> dict[str, Any]:
    """Every variant (module docstring) at ``points`` points; reasons for those that fail.

    ``float32``: an export folder of ``model`` to use (default: exported here).
    """
    with tempfile.TemporaryDirectory(prefix="taptr-onnx-gpu-") as scratch:
        return _all_variants(model, points, runs, Path(scratch), float32)


def _all_variants(
    model: torch.nn.Module, points: int, runs: int, root: Path, float32: str | None
) -> dict[str, Any]:
    """`onnx_cases` with a scratch folder ``root`` for the exports."""
    available = ort.get_available_providers()
    if float32 is None:
        export_v3(model, root / "float32")
    folders = {"float32": Path(float32) if float32 else root / "float32"}
    results: dict[str, Any] = {"providers": available}
    for kind, dtype in variants(available):
        if dtype not in folders:  # exported once, when a GPU variant asks for it
            folders[dtype] = export_half(model, root / dtype)
        needed = "TensorrtExecutionProvider" if kind == "tensorrt" else None
        if needed is not None and needed not in available:
            results[f"{kind}_{dtype}"] = f"unavailable: {needed} not in onnxruntime"
            continue
        try:
            half = dtype == "float16"
            results[f"{kind}_{dtype}"] = one_variant(
                str(folders[dtype]), kind, half, points, runs, root / "tensorrt-engines"
            )
        except Exception as error:  # a failing variant is reported, not fatal
            results[f"{kind}_{dtype}"] = f"failed: {type(error).__name__}: {str(error)[:300]}"
    return results
