"""Small index and scale tables kept per shape, device and dtype instead of rebuilt per call.

Sampling steps, level sizes, row offsets and frequency tables depend only on the frame's
level shapes, the heads and the device; building them from Python lists on every call
costs a handful of host-to-device copies and ``arange`` launches per layer and frame,
and a captured step (a CUDA graph, a compiled graph) wants them to be the same tensors
each time. `kept` makes a table once per key and hands back the same tensor afterwards.
Inside ``torch.compile`` the table is made in the graph (a constant there), not looked up.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable

import torch
from torch import Tensor

CAPACITY = 512
"""Tables kept at most; the least recently used goes first (one input size, one device
and one dtype need a few dozen)."""

_KEPT: OrderedDict[Hashable, Tensor] = OrderedDict()


def kept(key: Hashable, make: Callable[[], Tensor]) -> Tensor:
    """``make()``, made once per ``key`` (which must name the device and dtype it depends on).

    The table must never be written to: every caller shares it.
    """
    if torch.compiler.is_compiling():
        return make()
    table = _KEPT.get(key)
    if table is None:
        with torch.inference_mode(False), torch.no_grad():
            table = make()
        _KEPT[key] = table
        if len(_KEPT) > CAPACITY:
            _KEPT.popitem(last=False)
    else:
        _KEPT.move_to_end(key)
    return table
