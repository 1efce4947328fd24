"""Engines that run TAPTRv3's exported graphs, chosen by name, behind one small protocol.

An engine opens the three graphs of an export folder and runs them with numpy in and out
(`StepGraphs`: ``encode``, ``start_points``, ``decode_step``); the frame loop
(`taptr.onnx.frame_loop`) and the trackers above it never know which one runs:

- ``onnxruntime`` (`taptr.onnx.ort_engine`): presets ``cpu``, ``cuda``, ``cuda-graphs``
  (the step replayed as CUDA graphs over I/O binding) and ``tensorrt``;
- ``openvino`` (`taptr.onnx.openvino_engine`): Intel's inference engine for CPUs
  (device and inference precision as options).

Both are optional packages, imported only when their engine is opened; a missing one is
one line naming the extra that brings it. Before an engine opens a graph, the file must
be a regular file (`taptr.onnx.export_files`), and once open its inputs and outputs must
be the ones the manifest describes (`check_signature`): a graph swapped for another is
refused by name, not by an engine's missing-input error on the first frame.

These are engines of exported graphs; `taptr.runtime.engines` is something else, the
PyTorch model's own drivers (windows or frames).
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from taptr.messages import install_line
from taptr.onnx.export_files import require_regular
from taptr.onnx.v3_manifest import V3Manifest
from taptr.onnx.v3_tensors import GRAPHS


class StepGraphs(Protocol):
    """The three graphs of a TAPTRv3 export, numpy in and out."""

    manifest: V3Manifest

    def encode(self, frames: np.ndarray) -> np.ndarray:
        """Frames (F, 3, H, W) RGB in [0, 1] → memory (F, S, C)."""
        ...

    def start_points(
        self, memory: np.ndarray, positions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Memory (S, C), positions (N, 2) → content (N, C), context (N, K, K, C) or None."""
        ...

    def decode_step(self, inputs: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
        """``decode_step``'s named inputs → new positions (N, 4), visibility (N, 3), features."""
        ...


@dataclass(frozen=True)
class GraphEngine:
    """One engine: where its class lives and what installs it.

    Attributes:
        name: what ``engine=`` and ``--engine`` call it.
        opener: ``module:Class`` of its `StepGraphs`, taking the folder and options.
        package: the Python package it needs.
        extra: the taptr extra that installs it.
    """

    name: str
    opener: str
    package: str
    extra: str


ENGINES: dict[str, GraphEngine] = {
    engine.name: engine
    for engine in (
        GraphEngine(
            "onnxruntime", "taptr.onnx.ort_engine:OnnxRuntimeGraphs", "onnxruntime", "export"
        ),
        GraphEngine(
            "openvino", "taptr.onnx.openvino_engine:OpenVinoGraphs", "openvino", "openvino"
        ),
    )
}
"""Every engine by name."""


def engine_named(name: str) -> GraphEngine:
    """The engine called ``name``.

    Raises:
        ValueError: no engine has that name.
    """
    engine = ENGINES.get(name) if isinstance(name, str) else None
    if engine is None:
        raise ValueError(f"engine must be one of {', '.join(ENGINES)}, got {name!r}")
    return engine


def engine_module(engine: GraphEngine) -> Any:
    """The engine's package, imported.

    Raises:
        ModuleNotFoundError: it is not installed (the message names the extra).
    """
    try:
        return importlib.import_module(engine.package)
    except ImportError:
        raise ModuleNotFoundError(
            f"the {engine.name} engine needs {engine.package}: {install_line(engine.extra)}"
        ) from None


def open_graphs(
    directory: str | os.PathLike[str], engine: str = "onnxruntime", **options: Any
) -> StepGraphs:
    """The graphs of a TAPTRv3 export folder, opened by the engine called ``engine``.

    Args:
        directory: the export folder.
        engine: one of `ENGINES`.
        **options: the engine's own (`taptr.onnx.ort_engine.OnnxRuntimeGraphs`,
            `taptr.onnx.openvino_engine.OpenVinoGraphs`).

    Raises:
        ValueError: an unknown engine, or an export folder that fails its checks.
        ModuleNotFoundError: the engine's package is missing.
    """
    chosen = engine_named(engine)
    engine_module(chosen)  # its message before the manifest's
    module, name = chosen.opener.split(":")
    return getattr(importlib.import_module(module), name)(directory, **options)


def graph_files(manifest: V3Manifest, directory: str | os.PathLike[str]) -> dict[str, str]:
    """Each graph's file, checked to be a regular file before any engine opens it.

    Raises:
        FileNotFoundError: a graph is missing.
        ValueError: a graph is a folder, FIFO, device or socket.
    """
    return {
        name: str(require_regular(manifest.graph_path(directory, name), f"graph {name}"))
        for name in GRAPHS
    }


def check_signature(
    manifest: V3Manifest, name: str, path: str, inputs: Sequence[str], outputs: Sequence[str]
) -> None:
    """Refuses an opened graph whose input or output names are not the manifest's.

    Args:
        manifest: the export's.
        name: the graph the file should hold.
        path: its file, for the message.
        inputs: the opened graph's input names, in order.
        outputs: its output names, in order.

    Raises:
        ValueError: another graph's names (a file swapped for another).
    """
    expected = (manifest.input_names(name), manifest.output_names(name))
    found = (list(inputs), list(outputs))
    if found != expected:
        raise ValueError(
            f"{path} is not the {name} graph the manifest describes: inputs "
            f"{', '.join(found[0]) or 'none'}, outputs {', '.join(found[1]) or 'none'}; "
            f"expected inputs {', '.join(expected[0])}"
        )
