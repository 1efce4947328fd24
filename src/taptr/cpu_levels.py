"""``TAPTR_CPU``'s levels without torch: what the torch-free engines may take the CPU to have.

`taptr.model.ops.cpu_features` explains the levels and applies them to PyTorch's view of
the CPU; the exported-graph engines (`taptr.onnx`) run without torch and ask the same
question of their own engine, so the setting and its rule live here, below both.
"""

from __future__ import annotations

import functools
import os

VARIABLE = "TAPTR_CPU"
"""The setting that lowers what taptr takes the CPU to have."""

LEVELS = ("default", "avx2", "avx512", "avx512_bf16", "amx")
"""``TAPTR_CPU``'s values, from the least capable CPU to the most."""


@functools.cache
def ceiling() -> str:
    """The level ``TAPTR_CPU`` names, or ``amx`` (nothing taken away) when it is unset.

    Raises:
        ValueError: ``TAPTR_CPU`` is set to something else than one of `LEVELS`.
    """
    value = os.environ.get(VARIABLE, "").strip().lower()
    if not value:
        return LEVELS[-1]
    if value not in LEVELS:
        raise ValueError(f"{VARIABLE}={value!r} is no CPU level; choose from {', '.join(LEVELS)}")
    return value


def allowed(level: str) -> bool:
    """Whether instructions of ``level`` are left in by ``TAPTR_CPU``."""
    return LEVELS.index(level) <= LEVELS.index(ceiling())
