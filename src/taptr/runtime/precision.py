"""The type a model computes in: autocast names, and the context every model call runs in.

``float32`` runs the weights' own type throughout. On accelerators ``float16`` and
``bfloat16`` are ``torch.autocast``; on the CPU, ``bfloat16`` is oneDNN bfloat16 products
(`taptr.model.ops.dense.bfloat16_products`, with the trunk stored by
`taptr.model.taptr.TAPTR.bfloat16_trunk`). Denormal floats are flushed to zero on the CPU
whatever the type (`taptr.runtime.denormals`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

from taptr.model.ops.dense import bfloat16_products
from taptr.runtime.denormals import flushed_denormals
from taptr.types import AUTOCAST_TYPES


def autocast_type(name: str) -> torch.dtype | None:
    """The ``autocast`` of a `taptr.types.AUTOCAST_TYPES` name (``float32``: None, no autocast).

    Raises:
        ValueError: for another name; the message lists the known ones.
    """
    if name not in AUTOCAST_TYPES:
        raise ValueError(f"unknown dtype {name!r}; expected one of {', '.join(AUTOCAST_TYPES)}")
    return None if name == "float32" else getattr(torch, name)


@contextlib.contextmanager
def precision_context(device_type: str, autocast: torch.dtype | None) -> Iterator[None]:
    """The context a model runs in for an ``autocast`` type (None: float32 as it is).

    ``torch.autocast`` on accelerators; on the CPU, bfloat16 is oneDNN bfloat16 products,
    and denormal floats are flushed to zero. Entered when the block starts.
    """
    if autocast is None:
        products: contextlib.AbstractContextManager[object] = contextlib.nullcontext()
    elif autocast == torch.bfloat16 and device_type == "cpu":
        products = bfloat16_products()
    else:
        products = torch.autocast(device_type, dtype=autocast)
    with flushed_denormals(device_type), products:
        yield
