"""Linear layers as oneDNN inner products on x86 CPUs, at inference.

PyTorch runs a float32 ``F.linear`` on CPU through its BLAS (MKL in the official wheels),
which may pick AVX2 kernels on AMD CPUs where oneDNN, the library behind PyTorch's CPU
convolutions, runs AVX-512 ones: the same products can then differ by up to twice in rate.
The gap depends on the build and the host (docs/BENCHMARKS.md, ``benchmarks/gemm_floor.py``,
``benchmarks/host_choices.py``), so the predictor times both once per host and keeps the
faster (`taptr.runtime.cpu_choice`). The same sums in another order: results agree with
``F.linear`` up to float rounding.

oneDNN's inner product is reached through ``torch.ops.mkldnn._linear_pointwise``, the op
``torch.compile``'s CPU backend emits for linear layers. It has no backward, so it is used
only where autograd records nothing, and only where it exists: x86 CPUs (AVX2 or AVX-512;
elsewhere, as on Apple silicon, the BLAS is the vendor's own), float32, outside autocast
and outside graph capture (``torch.compile``, ``torch.export``, ``torch.jit.trace``).
Everywhere else `linear` is ``F.linear``.

Inside `bfloat16_products`, on CPUs that multiply bfloat16 natively (AVX512-BF16 or AMX,
`native_bfloat16`), those oneDNN products take bfloat16 inputs and weights (a bfloat16
copy of each weight, made once) and accumulate in float32; their results come back as
float32, except where the caller reads them in bfloat16 anyway or converts them itself
(``keep_type``: between the layers of an MLP, into row blocks). The decoder's key and value
tables are kept in bfloat16 (`bfloat16_table`), and so are the borderless rows a decoder
layer projects for one frame (TAPTRv3's keys, `taptr.model.ops.gather.projected_table`):
half their memory, half the bytes their row gathers read; the samples come back to
float32 before the scores.
Everything else that is not a product (norms, softmax, the sampling weights' sums,
sigmoids, the position update's sums) stays in float32. The backbone's convolutions run
in bfloat16 too where the model's trunk is stored so
(`taptr.model.taptr.TAPTR.bfloat16_trunk`).
"""

from __future__ import annotations

import contextlib
import contextvars
import math
import weakref
from collections.abc import Iterator

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.utils.flop_counter import register_flop_formula

# re-exported: where the products run is this module's question to callers
from taptr.model.ops.cpu_features import native_bfloat16 as native_bfloat16
from taptr.model.ops.cpu_features import onednn_available as onednn_available


def _inner_product_flops(x_shape: torch.Size, w_shape: torch.Size, *args, **kwargs) -> int:
    """2 per multiply-accumulate, as ``torch.utils.flop_counter`` counts ``F.linear``."""
    out_features, in_features = w_shape
    return 2 * math.prod(x_shape[:-1]) * in_features * out_features


if hasattr(torch.ops.mkldnn, "_linear_pointwise"):
    # without a formula, FlopCounterMode counts these products as zero
    register_flop_formula(torch.ops.mkldnn._linear_pointwise)(_inner_product_flops)


_PRODUCT_TYPE: contextvars.ContextVar[torch.dtype] = contextvars.ContextVar(
    "taptr_product_type", default=torch.float32
)


def product_type() -> torch.dtype:
    """The type `linear`'s oneDNN products run in here: bfloat16 inside `bfloat16_products`."""
    return _PRODUCT_TYPE.get()


@contextlib.contextmanager
def bfloat16_products() -> Iterator[None]:
    """Runs `linear`'s oneDNN products in bfloat16 inside the block (see the module notes).

    Raises:
        RuntimeError: this CPU has no native bfloat16 (`native_bfloat16`).
    """
    if not native_bfloat16():
        raise RuntimeError("this CPU has no native bfloat16 products (AVX512-BF16 or AMX)")
    token = _PRODUCT_TYPE.set(torch.bfloat16)
    try:
        yield
    finally:
        _PRODUCT_TYPE.reset(token)


_BFLOAT16_COPIES: dict[int, tuple[int, Tensor]] = {}
"""id(weight) → (its version when copied, the bfloat16 copy); an entry leaves with its weight."""


def _bfloat16_copy(tensor: Tensor) -> Tensor:
    """A bfloat16 copy of a float32 weight, made once per weight and version.

    A view of a weight (the query, key and value rows that attention slices off its packed
    ``in_proj_weight`` at every call) is a new tensor each call: it is read off the copy of
    the weight it views, so the conversion is not repeated per call.
    """
    base = tensor._base
    if base is not None and base.is_contiguous():
        offset = tensor.storage_offset() - base.storage_offset()
        return _bfloat16_copy(base).as_strided(tensor.size(), tensor.stride(), offset)
    key = id(tensor)
    kept = _BFLOAT16_COPIES.get(key)
    if kept is None:
        weakref.finalize(tensor, _BFLOAT16_COPIES.pop, key, None)
    if kept is None or kept[0] != tensor._version:
        kept = (tensor._version, tensor.detach().contiguous().to(torch.bfloat16))
        _BFLOAT16_COPIES[key] = kept
    return kept[1]


def onednn_applies(x: Tensor, weight: Tensor) -> bool:
    """Whether `linear` would run ``x`` (..., in) through oneDNN."""
    inputs = (torch.float32, torch.bfloat16) if bfloat16_mode() else (torch.float32,)
    if x.device.type != "cpu" or x.dtype not in inputs or weight.dtype != torch.float32:
        return False
    if torch.is_grad_enabled() and (x.requires_grad or weight.requires_grad):
        return False
    if torch.is_autocast_enabled("cpu") or _tracing():
        return False
    return onednn_available()


def _tracing() -> bool:
    """Whether a graph is being captured (compile, export, jit trace): graphs keep ``F.linear``."""
    exporting = getattr(torch.compiler, "is_exporting", lambda: False)
    return torch.compiler.is_compiling() or exporting() or torch.jit.is_tracing()


def bfloat16_mode() -> bool:
    """Whether this code runs inside `bfloat16_products`."""
    return _PRODUCT_TYPE.get() is torch.bfloat16


def linear(
    x: Tensor,
    weight: Tensor,
    bias: Tensor | None,
    *,
    onednn: bool,
    relu: bool = False,
    keep_type: bool = False,
) -> Tensor:
    """``F.linear(x, weight, bias)``, then ReLU if asked; through oneDNN where it applies.

    Args:
        x: (..., in) rows.
        weight: (out, in).
        bias: (out,) or None.
        onednn: the execution's choice (`taptr.model.execution.Execution.onednn_linear`);
            False always runs ``F.linear``.
        relu: apply ReLU to the result (fused into the product on the oneDNN path).
        keep_type: the caller takes the product's own type (the next `linear` of an MLP,
            or a ``copy_`` into a float32 buffer, which converts on the way): inside
            `bfloat16_products` the result stays bfloat16, saving a conversion pass.

    Returns:
        (..., out), float32 unless ``keep_type`` inside `bfloat16_products`.
    """
    if onednn and onednn_applies(x, weight):
        attr = "relu" if relu else "none"
        if bfloat16_mode():
            bias16 = None if bias is None else _bfloat16_copy(bias)
            out = torch.ops.mkldnn._linear_pointwise(
                x.to(torch.bfloat16), _bfloat16_copy(weight), bias16, attr, [], ""
            )
            return out if keep_type else out.float()
        return torch.ops.mkldnn._linear_pointwise(x, weight, bias, attr, [], "")
    out = F.linear(x, weight, bias)
    return F.relu(out) if relu else out


def bfloat16_table(layer: nn.Linear, x: Tensor, out: Tensor) -> Tensor:
    """``layer(x)`` written into ``out`` in bfloat16, inside `bfloat16_products`.

    For the decoder's key and value tables (`taptr.model.frame_tables`): kept in bfloat16
    they take half the memory and their row gathers read half the bytes, and a product
    written into a reused buffer skips the page faults of a fresh one that size.

    Shape:
        x (S, in) float32 or bfloat16; out (S, out_features) bfloat16.
    """
    bias = _bfloat16_copy(layer.bias)
    return torch.addmm(bias, x.to(torch.bfloat16), _bfloat16_copy(layer.weight).t(), out=out)


def apply_linear(
    layer: nn.Linear, x: Tensor, *, onednn: bool, relu: bool = False, keep_type: bool = False
) -> Tensor:
    """``layer(x)`` (then ReLU if asked) by `linear`: through oneDNN where it applies."""
    return linear(x, layer.weight, layer.bias, onednn=onednn, relu=relu, keep_type=keep_type)
