"""What every graph export shares: the ONNX opset and the exporters silenced.

Both families' graphs (`taptr.export.graphs` for TAPTR v1 and TAPTRv2,
`taptr.export.v3_graphs` for TAPTRv3) and the GPU benchmarks export through these.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Iterator
from contextlib import contextmanager

import torch

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
