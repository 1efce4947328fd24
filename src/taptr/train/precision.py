"""Mixed precision: the autocast context and the loss scaler of a precision setting.

``bf16`` autocasts with bfloat16 and needs no scaling; ``fp16`` autocasts with float16 and
scales the loss (a `torch.amp.GradScaler`, CUDA only); ``fp32`` does neither. On CPUs
without bfloat16 hardware, bf16 autocast is much slower than fp32: use it on GPUs.
"""

from __future__ import annotations

import contextlib
from typing import Any

import torch

DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


def autocast(precision: str, device: torch.device) -> contextlib.AbstractContextManager[Any]:
    """The context to run the forward in."""
    if precision == "fp32":
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=DTYPES[precision])


def grad_scaler(precision: str, device: torch.device) -> torch.amp.GradScaler:
    """A loss scaler, enabled only for fp16 on CUDA (a disabled one is a pass-through)."""
    if precision == "fp16" and device.type != "cuda":
        raise ValueError("precision fp16 needs a CUDA device; use bf16 or fp32 on CPU")
    return torch.amp.GradScaler(device.type, enabled=precision == "fp16")
