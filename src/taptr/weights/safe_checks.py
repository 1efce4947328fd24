"""Checks of a checkpoint's content that must not themselves be the weak point.

Messages about a file's content show it through `short_repr` (bounded in length and
depth: a repr of a value nested 100,000 deep recurses until it fails); the finiteness of
weights is checked by `all_finite` on at most the storage a tensor reads (a zero stride can
make a view of billions of elements over one stored number); a model config's shape is
bounded by `config_shape_problem` before its values are checked and printed; and
`named_failures` turns whatever else PyTorch raises on a strange file into one line
naming it.
"""

from __future__ import annotations

import contextlib
import os
import reprlib
from collections.abc import Iterator, Mapping
from typing import Any

import torch
from torch import Tensor

from taptr.io.file_kind import shown
from taptr.io.nesting import nesting_depth
from taptr.memory_estimate import allocator_failure

CONFIG_DEPTH = 3
"""Deepest nesting of a model config: the config, its backbone, the backbone's widths."""

CONFIG_ITEMS = 256
"""Most values in a model config, counting those inside lists and dicts (a preset has 30)."""

FINITE_CHUNK = 1 << 22
"""Elements checked at a time by `all_finite`: its temporaries stay at a few megabytes."""

_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxstring, _REPR.maxother = 2, 40, 40
_REPR.maxlist = _REPR.maxdict = _REPR.maxtuple = _REPR.maxset = 4


class CheckpointError(ValueError):
    """A checkpoint file cannot be used; the message names the file and the reason."""


class UnsafeCheckpointError(CheckpointError):
    """A checkpoint contains Python objects other than tensors and plain data."""


def short_repr(value: Any) -> str:
    """A short repr of data read from a file: bounded in length and depth, never recursing."""
    return _REPR.repr(value)


def key_name(key: Any) -> str:
    """A key of a file's dict for a message: names as they are, anything else as a short repr."""
    return key[:40] if isinstance(key, str) else short_repr(key)


def all_finite(tensor: Tensor) -> bool:
    """Whether every element of ``tensor`` is finite, never materialising more than its storage.

    A view that shows more elements than the storage span it reaches (zero or overlapping
    strides) is checked through that span instead: every element it shows lies there.
    Either way the check runs `FINITE_CHUNK` elements at a time.
    """
    if tensor.numel() == 0:
        return True
    span = 1 + sum((n - 1) * step for n, step in zip(tensor.shape, tensor.stride(), strict=True))
    if tensor.is_contiguous():
        flat = tensor.reshape(-1)
    elif tensor.numel() <= span:
        flat = tensor.flatten()  # a copy no larger than the storage span it views
    else:
        flat = tensor.new_empty(0).set_(
            tensor.untyped_storage(), tensor.storage_offset(), (span,), (1,)
        )
    return all(
        bool(torch.isfinite(flat[start : start + FINITE_CHUNK]).all())
        for start in range(0, flat.numel(), FINITE_CHUNK)
    )


def config_shape_problem(data: Mapping[str, Any]) -> str | None:
    """What is wrong with the shape of a model config (depth, size, keys), or None."""
    if nesting_depth(dict(data), CONFIG_DEPTH) > CONFIG_DEPTH:
        return f"values nested more than {CONFIG_DEPTH} levels deep"
    if _count_values(data) > CONFIG_ITEMS:
        return f"more than {CONFIG_ITEMS} values"
    if not all(isinstance(key, str) for key in data):
        return "a key that is not a name"
    return None


def _count_values(data: Any) -> int:
    """Values in ``data`` and the lists and dicts in it (its depth is already bounded)."""
    if isinstance(data, Mapping):
        return len(data) + sum(_count_values(v) for v in data.values())
    if isinstance(data, (list, tuple)):
        return len(data) + sum(_count_values(v) for v in data)
    return 0


_UNNAMED_FAILURES = (
    RuntimeError,
    TypeError,
    AttributeError,
    LookupError,
    OverflowError,
    RecursionError,
)
"""What PyTorch and the checks may raise on a strange file without naming it."""


@contextlib.contextmanager
def named_failures(path: str | os.PathLike[str]) -> Iterator[None]:
    """Turns an unnamed failure on a file's content into a one-line `CheckpointError`.

    An allocator's failure stays what it is: the command line words it with the knobs
    (`taptr.memory_estimate.allocator_failure`).
    """
    try:
        yield
    except _UNNAMED_FAILURES as error:
        if allocator_failure(error):
            raise
        reason = " ".join(str(error).split())[:200] or type(error).__name__
        raise CheckpointError(
            f"cannot use {shown(path)}: {type(error).__name__}: {reason}"
        ) from None
