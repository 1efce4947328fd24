"""The decoder's key and value tables, one pair per frame and layer, shared by windows.

Key-aware cross-attention projects every frame's memory with each layer's key and value
projections. Those tables depend on the frame alone, not on the points, and windows
overlap (8 frames every 4), so each frame would be projected twice: 57 GFLOP per frame of
the paper model at 512 × 512, the largest part of the decoder. `FrameTables` projects each
(layer, frame) pair once and keeps the pairs of the frames the next window will read, and
nothing else: a few frames' tables at any time, not the video's.

It is explicit state: the window driver keeps one in its `TrackerState` and names each
window before decoding it (`FrameTables.start_window`); a decoder called without one makes
a throwaway store that keeps nothing. The tables are the borderless gather tables of
`taptr.model.ops.gather.projected_table`, made without gradients (inference only).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import torch
from torch import Tensor, nn

from taptr.model.ops.dense import apply_linear, bfloat16_mode, bfloat16_table, onednn_applies
from taptr.model.ops.row_blocks import autocasting

KeyValue = tuple[Tensor, Tensor]
"""One image's key and value tables, each (S, C): the memory's rows through one layer's
key and value projections, bias included (bfloat16 inside `dense.bfloat16_products`)."""


class FrameTables:
    """Key and value tables of each (layer, image of the batch, frame), kept across windows.

    Attributes:
        frames: the video frames of the current window, in order.
        keep_from: tables of frames from here on are kept for the next window; None keeps
            none.
        projections: how many (layer, image) pairs were projected so far (each pair is
            two products of S × C by C × C).
    """

    def __init__(self) -> None:
        self.frames: range = range(0)
        self.keep_from: int | None = None
        self.projections = 0
        # Each pair is one (2, S, C) tensor: at 512 × 512 that is above glibc's largest
        # mmap threshold (32 MB), so tables never share the heap with the encoder's
        # temporaries. A fresh allocation that size is a fresh mapping whose every page
        # faults on first write, so pairs no longer needed are written over instead.
        self._kept: dict[tuple[int, int, int], Tensor] = {}
        self._spare: list[Tensor] = []

    def start_window(self, first: int, last: int, keep_from: int | None) -> None:
        """Names the window about to be decoded and drops tables no later window reads.

        Args:
            first: first frame of the window.
            last: last frame (inclusive).
            keep_from: first frame of the next window: the window's tables from that
                frame on are kept; None keeps none.
        """
        self.frames = range(first, last + 1)
        self.keep_from = keep_from
        for key in [key for key in self._kept if key[2] < first]:
            self._spare.append(self._kept.pop(key))

    @property
    def kept_frames(self) -> list[int]:
        """The frames whose tables are kept, in order."""
        return sorted({frame for _, _, frame in self._kept})

    def images(
        self,
        layer: int,
        memory: Tensor,
        key_proj: nn.Linear,
        value_proj: nn.Linear,
        *,
        onednn: bool = False,
    ) -> Iterator[KeyValue]:
        """Layer ``layer``'s tables of each image of the window, in order, one at a time.

        A pair no later window reads is written over once the next one is asked for, so
        only one such pair exists at a time: consume each before asking for the next.

        Args:
            layer: the decoder layer.
            memory: (B·W_t, S, C) memory of the window's frames, image b·W_t + t.
            key_proj: the layer's key projection.
            value_proj: the layer's value projection.
            onednn: project through oneDNN where that applies (`taptr.model.ops.dense`).

        Yields:
            (keys, values), each (S, C), for images 0 .. B·W_t − 1.
        """
        for image in range(memory.shape[0]):
            batch, offset = divmod(image, len(self.frames))
            frame = self.frames[offset]
            key = (layer, batch, frame)
            keep = self.keep_from is not None and frame >= self.keep_from
            pair = self._kept.get(key) if keep else self._kept.pop(key, None)
            if pair is None:
                pair = self._project(memory[image], key_proj, value_proj, onednn)
                if keep:
                    self._kept[key] = pair
            yield pair[0], pair[1]
            if not keep:  # this layer was the last to read it
                self._spare.append(pair)

    def _project(
        self, memory: Tensor, key_proj: nn.Linear, value_proj: nn.Linear, onednn: bool
    ) -> Tensor:
        """(S, C) memory → its keys and values (2, S, C), bias included, without gradients.

        Inside `bfloat16_products` the pair is bfloat16 (`dense.bfloat16_table`): the
        memory is converted once for both products, and the gathers read half the bytes.
        """
        self.projections += 1
        with torch.no_grad():
            if onednn and bfloat16_mode() and onednn_applies(memory, key_proj.weight):
                pair = self._empty((2, *memory.shape), memory, torch.bfloat16)
                memory16 = memory.to(torch.bfloat16)
                bfloat16_table(key_proj, memory16, pair[0])
                bfloat16_table(value_proj, memory16, pair[1])
                return pair
            pair = self._empty((2, *memory.shape), memory)
            for projection, table in zip((key_proj, value_proj), pair, strict=True):
                if onednn and onednn_applies(memory, projection.weight):
                    # oneDNN writes a fresh tensor: copied into the reused pair (see __init__)
                    table.copy_(apply_linear(projection, memory, onednn=True))
                elif autocasting(memory):
                    table.copy_(projection(memory))
                else:
                    torch.addmm(projection.bias, memory, projection.weight.t(), out=table)
        return pair

    def _empty(
        self, shape: tuple[int, ...], like: Tensor, dtype: torch.dtype | None = None
    ) -> Tensor:
        """A spare tensor of ``shape``, else a new one.

        It is placed like ``like`` and typed ``dtype`` (default: ``like``'s type).
        """
        dtype = dtype or like.dtype
        for index, spare in enumerate(self._spare):
            if spare.shape == shape and spare.dtype == dtype and spare.device == like.device:
                return self._spare.pop(index)
        return like.new_empty(shape, dtype=dtype)


class LayerTables(NamedTuple):
    """One decoder layer's view of a `FrameTables`: what its cross-attention is given."""

    store: FrameTables
    layer: int

    def images(
        self, memory: Tensor, key_proj: nn.Linear, value_proj: nn.Linear, *, onednn: bool = False
    ) -> Iterator[KeyValue]:
        """`FrameTables.images` for this layer."""
        return self.store.images(self.layer, memory, key_proj, value_proj, onednn=onednn)


def window_store(tables: FrameTables | None, frames: int) -> FrameTables:
    """``tables``, checked against the window's ``frames``, or a throwaway store for it."""
    if tables is not None:
        if len(tables.frames) != frames:
            raise ValueError(
                f"the key and value tables were started for a window of "
                f"{len(tables.frames)} frames; the decoder was given {frames}"
            )
        return tables
    store = FrameTables()
    store.start_window(0, frames - 1, keep_from=None)
    return store
