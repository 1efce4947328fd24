"""How many operations a frame dispatches, and how many of them make the host wait.

On a GPU the arithmetic of a tracking step is small; its time goes to launching each
operation and to host synchronisations (an ``.item()``, a ``nonzero``, a boolean-mask
index: the host stops until the device has caught up). `count_frame_ops` runs a model on
random frames under a ``TorchDispatchMode`` and counts, per frame, every ATen operation
that launches a kernel (views, reshapes and bare allocations do not) and those that would
synchronise a GPU. It runs on any device; on a CPU, "as on a GPU" means without the CPU's
row blocks and query blocks (`taptr.model.execution.Execution`), which a GPU never takes.

``taptr bench --count-ops`` prints these counts; tests pin them.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Callable
from typing import Any, NamedTuple

import torch
from torch import Tensor
from torch.utils._python_dispatch import TorchDispatchMode

from taptr.model.taptr import TAPTR, normalize_frames
from taptr.model.trajectory import QuerySet

NO_LAUNCH = frozenset(
    {"empty", "empty_like", "new_empty", "empty_strided", "new_empty_strided", "detach"}
)
"""Operations that allocate or relabel memory without running a kernel."""

SYNCHRONISING = frozenset(
    {"_local_scalar_dense", "nonzero", "masked_select", "unique", "_unique2", "equal"}
)
"""Operations whose result size or value the host must read from the device."""


class OpCount(NamedTuple):
    """Operations per frame of a tracking run, after its first step.

    The first step (TAPTRv3's first frame, TAPTRv2's first window) also makes the points'
    contents and reads their start frames once; the counts are of the steps after it,
    per frame: what every further frame of a long video costs.

    Attributes:
        per_frame: kernel-launching operations per frame (encoder and decoder).
        syncs_per_frame: of those, the ones that make the host wait for the device.
        first_step: operations of the first step, its syncs included, for reference.
        by_name: operation name → count per frame, most frequent first.
    """

    per_frame: float
    syncs_per_frame: float
    first_step: int
    by_name: dict[str, float]


class _Counter(TorchDispatchMode):
    """Counts the ATen operations dispatched inside it."""

    def __init__(self) -> None:
        super().__init__()
        self.launches: Counter[str] = Counter()
        self.syncs = 0

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        name = func.overloadpacket.__name__
        if not func.is_view and name not in NO_LAUNCH:
            self.launches[name] += 1
            if name in SYNCHRONISING or _mask_index(name, args):
                self.syncs += 1
        return func(*args, **(kwargs or {}))


def _mask_index(name: str, args: Any) -> bool:
    """Whether an indexing operation takes a boolean mask (its size depends on the data)."""
    if name not in ("index", "index_put", "index_put_") or len(args) < 2:
        return False
    return any(isinstance(i, Tensor) and i.dtype == torch.bool for i in args[1] or ())


def as_on_accelerator(model: TAPTR) -> TAPTR:
    """The model without the CPU-only blocking: every MLP, encoder layer and query at once."""
    execution = dataclasses.replace(
        model.execution, row_block=None, encoder_block=None, sample_block=None
    )
    return model.set_execution(execution)


def count_frame_ops(
    model: TAPTR,
    size: tuple[int, int],
    points: int,
    frames: int = 8,
    seed: int = 0,
) -> OpCount:
    """Counts what tracking ``points`` points through ``frames`` random frames dispatches.

    The run is made twice, the second one counted, so that tables made once per shape
    (`taptr.model.ops.constants`) are not counted. Frames are encoded one per call, as
    they arrive in a stream; every point starts on frame 0.

    Args:
        model: the network, in evaluation mode, on the device to count on.
        size: (H, W) of the frames the model sees.
        points: N.
        frames: T, the video length: at least two steps (TAPTRv3: 2 frames; windows:
            one window and a stride more).
        seed: seed of the frames and points.
    """
    from taptr.runtime.engines import run_tracker
    from taptr.runtime.frames import EncodedFrames

    device = next(model.parameters()).device
    generator = torch.Generator().manual_seed(seed)
    video = torch.rand(1, frames, 3, *size, generator=generator).to(device)
    positions = (torch.rand(1, points, 2, generator=generator) * 0.9 + 0.05).to(device)
    queries = QuerySet(
        torch.zeros(1, points, dtype=torch.long, device=device),
        positions,
        torch.ones(1, points, dtype=torch.bool, device=device),
    )

    def track(on_step: Callable[[], object] | None = None) -> None:
        source = EncodedFrames(model, lambda a, b: normalize_frames(video[:, a : b + 1]), 1, frames)
        run_tracker(model, queries, frames, source, torch.float32, on_step)

    counter = _Counter()
    marks: list[tuple[Counter[str], int]] = []
    with torch.no_grad():
        track()
        with counter:
            track(lambda: marks.append((counter.launches.copy(), counter.syncs)))
    first, first_syncs = marks[0]
    later = counter.launches - first
    span = frames - (model.window_size if len(marks) > 1 else 0)
    if span <= 0:
        raise ValueError(f"{frames} frames make a single step: count at least two steps")
    by_name = {name: count / span for name, count in later.most_common()}
    return OpCount(
        sum(later.values()) / span,
        (counter.syncs - first_syncs) / span,
        sum(first.values()),
        by_name,
    )
