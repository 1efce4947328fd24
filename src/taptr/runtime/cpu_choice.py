"""The CPU execution's product library and frame layout, chosen by measuring them there.

Two settings of the ``fast`` execution were tuned on particular CPUs and change speed only:

- **Products**: oneDNN inner products (`taptr.model.ops.dense`) or the BLAS for the linear
  layers: either may be the faster, by the CPU and the build (docs/BENCHMARKS.md). Timed on
  the model's own encoder FFN, a block of rows.
- **Layout**: channels-last frames into the backbone, used from `CHANNELS_LAST_MIN_PIXELS`
  up, where it pays on the CPUs measured. Timed on the backbone at the input size where the
  rule would use it; below the threshold frames stay as they are.

Each is timed once per machine, model and input size and remembered
(`taptr.runtime.measured`). Inside `dense.bfloat16_products` the products stay oneDNN's,
the only path with bfloat16 kernels.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import torch

from taptr.model.execution import CHANNELS_LAST_MIN_PIXELS, Execution
from taptr.model.ops.dense import bfloat16_mode, onednn_available
from taptr.model.ops.row_blocks import ENCODER_BLOCK
from taptr.model.taptr import TAPTR
from taptr.runtime.measured import TOLERANCE, best_seconds, choice_key, remembered

CPU = torch.device("cpu")


def _own_setting_holds(key: str, time_both: Callable[[], dict[bool, float]]) -> bool:
    """Whether the execution's own setting (True) is kept against the other (False).

    Measured the first time ``key`` is asked for, then remembered: the other setting
    replaces it only when it is `TOLERANCE` faster.
    """

    def measure() -> bool:
        seconds = time_both()
        return not seconds[False] < seconds[True] * (1 - TOLERANCE)

    return bool(remembered(key, measure, valid=lambda value: isinstance(value, bool)))


@torch.no_grad()
def time_products(model: TAPTR) -> dict[bool, float]:
    """Seconds of the first encoder layer's FFN on a block of rows, by ``onednn_linear``."""
    ffn = model.encoder.layers[0].ffn
    dtype = next(model.input_projections.parameters()).dtype
    rows = torch.randn(ENCODER_BLOCK, ffn.layers[0].in_features, dtype=dtype)
    settings = {o: dataclasses.replace(model.execution, onednn_linear=o) for o in (True, False)}
    return {
        onednn: best_seconds(lambda e=execution: ffn(rows, e), CPU)
        for onednn, execution in settings.items()
    }


@torch.no_grad()
def time_layouts(model: TAPTR, input_size: tuple[int, int]) -> dict[bool, float]:
    """Seconds of `TAPTR.feature_maps` on one frame, by ``channels_last``."""
    dtype = next(model.input_projections.parameters()).dtype
    frame = torch.randn(1, 3, *input_size, dtype=dtype)
    own = model.execution
    seconds = {}
    try:
        for layout in (True, False):
            model.set_execution(dataclasses.replace(own, channels_last=layout))
            seconds[layout] = best_seconds(lambda: model.feature_maps(frame), CPU)
    finally:
        model.set_execution(own)
    return seconds


def choose_cpu_execution(model: TAPTR, input_size: tuple[int, int]) -> Execution:
    """Sets the CPU execution's products and layout to the faster, measured; returns it.

    Only the settings the execution uses are questioned (an execution without oneDNN
    products or channels-last is left as it is), and only where both choices would run.
    """
    execution = model.execution
    signature = repr(model.config)
    products = execution.onednn_linear and onednn_available() and not bfloat16_mode()
    if products and model.encoder.layers:
        key = choice_key("oneDNN products", CPU, signature, "encoder FFN")
        onednn = _own_setting_holds(key, lambda: time_products(model))
        execution = dataclasses.replace(execution, onednn_linear=onednn)
    pixels = input_size[0] * input_size[1]
    if execution.channels_last and pixels >= CHANNELS_LAST_MIN_PIXELS:
        trunk = next(model.backbone.parameters()).dtype
        shape = f"{input_size[0]}x{input_size[1]} trunk {trunk}"
        key = choice_key("channels-last frames", CPU, signature, shape)
        layout = _own_setting_holds(key, lambda: time_layouts(model, input_size))
        execution = dataclasses.replace(execution, channels_last=layout)
    model.set_execution(execution)
    return execution
