"""How a model runs: the named execution modes, one choice per model.

Every mode computes the same function; they differ in how, and their outputs agree up to
float rounding (tests/test_model.py checks ``reference`` against ``fast``). The mode is
chosen when the model is built (``build_model(config, execution="fast")``), changed only
through `taptr.model.taptr.TAPTR.set_execution`, and handed down from the top-level module
to the encoder, the decoder and their attentions as an argument: no submodule holds a mode.

- ``reference``: the straightforward formulation, what the official code computes and the
  benchmarks' baseline: ``grid_sample`` deformable attention, explicit N × N point-attention
  masks, every MLP on all its rows at once.
- ``fast``: the default for inference: deformable attention as weighted row gathers
  (`taptr.model.ops.gather`), point attention on the tracked points of each frame only
  (`taptr.model.ops.point_attention`), MLPs and encoder layers in cache-sized row blocks
  (`taptr.model.ops.row_blocks`), the decoder's key and value tables made once per frame
  and shared by the windows that overlap on it, frames channels-last into the backbone,
  its batch norms in place, linear layers as oneDNN inner products on x86 CPUs, and
  TAPTRv3's long-temporal attention through per-head query products, and its
  cross-attention's values projected after sampling where that costs less.
- ``training``: what `taptr.train` builds. The ``grid_sample`` kernel, because its backward
  is about half the cost of the gather kernel's on CPU (``embedding_bag``'s backward sorts
  every index: 2.4 vs 4.0 s per small-preset step); grouped point attention; and row blocks
  of ``ROW_BLOCK`` rows, which only apply where autograd records nothing (the periodic
  evaluation of the EMA copy): training steps themselves run every MLP on all rows at once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from taptr.model.ops.gather import CHUNK_ELEMENTS as SAMPLE_BLOCK
from taptr.model.ops.row_blocks import ENCODER_BLOCK, ROW_BLOCK

Kernel = Literal["grid_sample", "gather"]
"""A deformable-attention kernel of `taptr.model.ops`."""


@dataclass(frozen=True)
class Execution:
    """One way of running the model; outputs agree across executions up to rounding.

    Attributes:
        name: the preset's name (a key of `EXECUTIONS`).
        kernel: deformable-attention kernel, ``grid_sample`` (reference) or ``gather``.
        grouped_point_attention: run point self-attention on each frame's tracked points
            only, instead of on all N points with an N × N mask.
        row_block: MLPs at inference take their rows this many at a time; None runs all
            rows at once.
        encoder_block: encoder layers at inference take their tokens this many at a time
            after the value table (`taptr.model.encoder.EncoderLayer`); None runs all
            tokens at once.
        shared_tables: the decoder's key and value tables are made once per frame and
            layer and shared by the overlapping windows that hold the frame (``gather``
            kernel, inference only; `taptr.model.frame_tables`), instead of each window
            projecting all of its frames' memory in every layer.
        channels_last: frames of at least `CHANNELS_LAST_MIN_PIXELS` enter the backbone
            in channels-last (NHWC) memory order, which oneDNN's CPU convolutions run
            faster there; the feature maps then flatten into tokens without a transpose
            copy. Same values up to rounding.
        in_place_norms: the ResNet-50's frozen batch norms write into the convolution
            outputs they normalise (one pass, no new tensor) instead of two fresh
            tensors each; inference only, the same values (`taptr.model.backbone`).
        onednn_linear: linear layers at inference run as oneDNN inner products on x86
            CPUs in float32 (`taptr.model.ops.dense`), where they may run wider kernels
            than the BLAS product ``F.linear`` runs. Elsewhere, and where
            autograd records, they run ``F.linear``. Same values up to rounding.
        history_products: TAPTRv3's long-temporal attention scores and mixes the held
            frames through per-head products of each query instead of projecting every
            held frame (`taptr.model.ops.history_attention`): the same sums, about 30
            times fewer products on long histories.
        sample_block: on CPUs, TAPTRv3's context-aware attention samples key patches for
            blocks of queries of at most this many sampled elements (each block's samples
            stay below the allocator's mmap threshold); None takes all queries at once.
            Accelerators bound the blocks by memory only
            (`taptr.model.ops.context_patches.sample_block`).
        values_after_sampling: TAPTRv3's context-aware attention samples the memory and
            projects each point's sampled vector, instead of projecting every token into a
            value table, where that costs less for the frame's shape
            (`taptr.model.ops.memory_values`): the same sums in another order.
    """

    name: str
    kernel: Kernel
    grouped_point_attention: bool
    row_block: int | None
    encoder_block: int | None = None
    shared_tables: bool = False
    channels_last: bool = False
    in_place_norms: bool = False
    onednn_linear: bool = False
    history_products: bool = False
    sample_block: int | None = SAMPLE_BLOCK
    values_after_sampling: bool = False


CHANNELS_LAST_MIN_PIXELS = 192 * 192
"""Frames smaller than this enter the backbone as they are: below it the reordering into
channels-last costs more than oneDNN's faster convolutions save (measured:
docs/BENCHMARKS_LOG.md)."""


EXECUTIONS: dict[str, Execution] = {
    "reference": Execution("reference", "grid_sample", False, None),
    "fast": Execution(
        "fast",
        "gather",
        True,
        ROW_BLOCK,
        encoder_block=ENCODER_BLOCK,
        shared_tables=True,
        channels_last=True,
        in_place_norms=True,
        onednn_linear=True,
        history_products=True,
        values_after_sampling=True,
    ),
    "training": Execution("training", "grid_sample", True, ROW_BLOCK),
}
"""The named executions, by name."""

DEFAULT_EXECUTION = "fast"
"""What `taptr.model.build.build_model` picks unless told otherwise."""


def get_execution(execution: str | Execution) -> Execution:
    """The execution of a name (an `Execution` is returned as it is).

    Raises:
        ValueError: for an unknown name; the message lists the known ones.
    """
    if isinstance(execution, Execution):
        return execution
    if execution not in EXECUTIONS:
        names = ", ".join(EXECUTIONS)
        raise ValueError(f"unknown execution {execution!r}; choose from {names}")
    return EXECUTIONS[execution]
