"""The precision an engine runs the exported graphs in: ``float32``, ``bfloat16``, ``int8``.

The names are `taptr.api.spec.ModelSpec`'s ``dtype`` values, so a spec's precision reaches
an engine as it is. What each engine does with them:

- ``float32``: the graphs as exported, in both engines;
- ``bfloat16``: OpenVINO's inference precision hint, on CPUs with AVX512-BF16 or AMX
  (`taptr.onnx.openvino_engine`); onnxruntime's CPU provider has no bfloat16 kernels for
  these graphs and refuses it;
- ``int8``: the export's int8 graphs (`taptr.onnx.int8_graphs`, made once and kept), in
  both engines.

A precision an engine or the CPU cannot do is refused in one line, before any graph is
compiled: a silent fallback to float32 would report the wrong speed and accuracy.
"""

from __future__ import annotations

import os

from taptr.onnx.graph_engines import graph_files
from taptr.onnx.int8_graphs import int8_files
from taptr.onnx.v3_manifest import V3Manifest

PRECISIONS = ("float32", "bfloat16", "int8")
"""Every precision name an engine takes."""


class PrecisionError(ValueError):
    """A precision that this engine or this CPU does not run (one line, naming what can)."""


def check_precision(precision: str) -> str:
    """``precision`` when it is one of `PRECISIONS`.

    Raises:
        ValueError: any other value.
    """
    if precision not in PRECISIONS:
        raise PrecisionError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    return precision


def precision_files(
    directory: str | os.PathLike[str], manifest: V3Manifest, precision: str
) -> dict[str, str]:
    """Each graph's file for ``precision``: the export's, or its int8 ones for ``int8``.

    Raises:
        ValueError: an unknown precision or a graph that is not a regular file.
        FileNotFoundError: a graph is missing.
    """
    if check_precision(precision) == "int8":
        graph_files(manifest, directory)  # the export's own files checked first
        return int8_files(directory, manifest)
    return graph_files(manifest, directory)
