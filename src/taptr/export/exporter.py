"""What every graph export shares: the ONNX opset and the exporters silenced.

Both families' graphs (`taptr.export.graphs` for TAPTR v1 and TAPTRv2,
`taptr.export.v3_graphs` for TAPTRv3) and the GPU benchmarks export through these.
"""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import torch

from taptr.messages import install_line

ONNX_OPSET = 18
"""The dynamo exporter's opset; GridSample needs 16 or later."""


@contextmanager
def quiet_exporter() -> Iterator[None]:
    """Silences the exporters' notes, which are about their internals, not about ours.

    The ONNX optimiser logs a warning per multi-output op it does not fold, the dynamo
    exporter one per dynamic axis it renames, and TorchScript its deprecation and the
    tracer's notes on Python values (sizes here, which stay symbolic).
    """
    optimizer_log = logging.getLogger("onnxscript")
    level = optimizer_log.level
    optimizer_log.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            warnings.simplefilter("ignore", FutureWarning)
            warnings.simplefilter("ignore", DeprecationWarning)
            warnings.simplefilter("ignore", torch.jit.TracerWarning)
            yield
    finally:
        optimizer_log.setLevel(level)


def require_onnx_exporter() -> None:
    """Raises ModuleNotFoundError, naming the extra, where onnx or onnxscript is missing."""
    try:
        import onnx  # noqa: F401  (the dynamo exporter needs both)
        import onnxscript  # noqa: F401
    except ImportError:
        raise ModuleNotFoundError(
            f"ONNX export needs onnx and onnxscript: {install_line('export')}"
        ) from None


def export_onnx_graph(
    module: torch.nn.Module,
    inputs: tuple[torch.Tensor, ...],
    path: str | os.PathLike[str],
    names: tuple[list[str], list[str]],
    dynamic_shapes: Any,
) -> None:
    """Writes one graph through the dynamo exporter, at `ONNX_OPSET`, weights inside.

    Args:
        module: the graph's module (its forward takes ``inputs``).
        inputs: example inputs.
        path: the ``.onnx`` file.
        names: (input names, output names) of the graph.
        dynamic_shapes: per input, its dynamic dimensions (``torch.export``'s form).
    """
    input_names, output_names = names
    with quiet_exporter():
        torch.onnx.export(
            module,
            inputs,
            str(path),
            input_names=input_names,
            output_names=output_names,
            dynamic_shapes=dynamic_shapes,
            opset_version=ONNX_OPSET,
            dynamo=True,
            external_data=False,
            verbose=False,
        )
