"""What this CPU can do, as taptr sees it, and how to make it see less (``TAPTR_CPU``).

Some of taptr's choices depend on the CPU's instructions: oneDNN's inner products serve x86
CPUs with AVX2 or AVX-512 (`onednn_available`), and bfloat16 products
need AVX512-BF16 or AMX (`native_bfloat16`). Each branch must work on
every CPU, but a host only has one set of instructions, so ``TAPTR_CPU`` makes taptr take
the branches of a lesser CPU: taptr then behaves as on a CPU whose best instructions are
the level named, and every instruction above it is treated as missing. It only takes away:
naming a level this CPU does not reach changes nothing.

Levels, from least to most: ``default`` (no vector instructions taptr uses: the branch of
ARM and other non-x86 CPUs, plain ``F.linear``), ``avx2``, ``avx512`` (AVX-512 without
bfloat16), ``avx512_bf16``, ``amx``. For example ``TAPTR_CPU=avx512`` runs an AMD EPYC or
a Sapphire Rapids Xeon as a Xeon without bfloat16 would run. PyTorch's own kernels are
unchanged (``ATEN_CPU_CAPABILITY=avx2`` and ``ONEDNN_MAX_CPU_ISA=AVX2`` lower those, read by
PyTorch when it starts). Read once per process, like the CPU itself; tests that change it
call `refresh`.
"""

from __future__ import annotations

import functools

import torch

from taptr.cpu_levels import LEVELS as LEVELS
from taptr.cpu_levels import VARIABLE as VARIABLE
from taptr.cpu_levels import allowed as _allowed
from taptr.cpu_levels import ceiling as ceiling

X86_CAPABILITIES = ("AVX2", "AVX512")
"""``torch.backends.cpu.get_cpu_capability()`` values of the CPUs the oneDNN path serves
(lowered by ``TAPTR_CPU``)."""

_CAPABILITY_LEVEL = {"DEFAULT": "default", "AVX2": "avx2", "AVX512": "avx512"}
"""``torch.backends.cpu.get_cpu_capability()`` → level (other values: no x86 level)."""


def cpu_capability() -> str:
    """``torch.backends.cpu.get_cpu_capability()``, lowered to ``TAPTR_CPU``'s level.

    ``AVX512`` becomes ``AVX2`` under ``TAPTR_CPU=avx2``, and either becomes ``DEFAULT``
    under ``TAPTR_CPU=default``; other values (an ARM CPU's) are as PyTorch says.
    """
    found = torch.backends.cpu.get_cpu_capability()
    level = _CAPABILITY_LEVEL.get(found)
    if level is None or _allowed(level):
        return found
    return ceiling().upper() if ceiling() in ("default", "avx2") else "AVX512"


def bfloat16_hardware() -> dict[str, bool]:
    """This CPU's bfloat16 instructions as PyTorch sees them: ``avx512_bf16``, ``amx``.

    Each is False where ``TAPTR_CPU`` takes it away.
    """
    found = {
        "avx512_bf16": bool(getattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False)()),
        "amx": bool(getattr(torch.cpu, "_is_amx_tile_supported", lambda: False)()),
    }
    return {name: has and _allowed(name) for name, has in found.items()}


@functools.cache
def onednn_available() -> bool:
    """Whether this PyTorch build and CPU have oneDNN's inner product (fixed per process)."""
    if not torch.backends.mkldnn.is_available():
        return False
    if cpu_capability() not in X86_CAPABILITIES:
        return False
    return hasattr(torch.ops.mkldnn, "_linear_pointwise")


@functools.cache
def native_bfloat16() -> bool:
    """Whether this CPU multiplies bfloat16 natively (AVX512-BF16 or AMX) through oneDNN.

    False where ``TAPTR_CPU`` takes both away.
    """
    if not onednn_available():
        return False
    has = any(bfloat16_hardware().values())
    return has and bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())


def simulated() -> str | None:
    """The level ``TAPTR_CPU`` names when it takes anything away, for records; else None."""
    return None if ceiling() == LEVELS[-1] else ceiling()


def refresh() -> None:
    """Reads ``TAPTR_CPU`` again, and forgets every answer that depended on it."""
    ceiling.cache_clear()
    onednn_available.cache_clear()
    native_bfloat16.cache_clear()
