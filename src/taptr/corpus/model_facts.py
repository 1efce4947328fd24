"""What a `ModelSpec`'s tracker is, read from its checkpoint without building it.

The driver of a corpus needs two things of the model before any actor starts: the
settings digest of every video (`taptr.corpus.settings`) and the memory each actor
reserves (`taptr.corpus.cluster.actor_memory`). Both follow from the checkpoint's config,
its file, its calibrated threshold and the spec, so the driver reads the file (checked as
the loader checks it, `taptr.weights.checkpoint.checkpoint_contents`) and builds nothing: no
weights are copied into a model, no predictor times its kernels, nothing moves to a GPU.
The weights' size is counted on PyTorch's meta device (no memory).

A name resolves through `taptr.weights.registry.resolve_weights`, as loading resolves it, in
the same order and with the same warnings (an untrained preset, the bundled model standing in
for the default).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from taptr.api.spec import ModelSpec
from taptr.config import SUPPORT_KINDS, check_history_frames
from taptr.types import AUTOCAST_TYPES, ENGINE_CHOICES
from taptr.weights.checkpoint_facts import checkpoint_facts

if TYPE_CHECKING:
    from taptr.config import ModelConfig


@dataclass(frozen=True)
class ModelFacts:
    """A tracker's settings as its predictor would hold them, and its weights' size.

    Attributes mirror `taptr.api.predictor.Predictor` (what `taptr.settings_record`
    reads), so that a digest made from them equals one made from the predictor.

    Attributes:
        source: the name or file it was asked as (``Predictor.source``).
        checkpoint_path: the file its weights come from (None: an untrained preset).
        config: its model config.
        visibility_threshold: the file's calibrated threshold, else the config's.
        input_size: (H, W) the model sees.
        context_points: TAPTRv2's context points K.
        support_points: the support asked for (None: the model's own).
        history_frames: TAPTRv3's history limit asked for (None: the model's).
        weight_bytes: bytes of its parameters as loaded (float32).
    """

    source: str
    checkpoint_path: Path | None
    config: ModelConfig
    visibility_threshold: float
    input_size: tuple[int, int]
    context_points: int
    support_points: str | None
    history_frames: int | None
    weight_bytes: int


def check_spec(spec: ModelSpec) -> None:
    """Refuses a spec whose values no predictor takes, before any file is read.

    Raises:
        ValueError: names the field and the values it takes.
    """
    if spec.dtype not in AUTOCAST_TYPES:
        raise ValueError(f"dtype must be one of {', '.join(AUTOCAST_TYPES)}, got {spec.dtype!r}")
    if spec.engine not in ENGINE_CHOICES:
        names = ", ".join(ENGINE_CHOICES)
        raise ValueError(f"engine must be one of {names}, got {spec.engine!r}")
    if spec.support is not None and spec.support not in SUPPORT_KINDS:
        kinds = ", ".join(SUPPORT_KINDS)
        raise ValueError(f"support must be one of {kinds} or None, got {spec.support!r}")
    points = spec.context_points
    if points is not None and (type(points) is not int or points < 0):
        raise ValueError(f"context_points must be a whole number >= 0, got {points!r}")
    if spec.history_frames is not None:
        check_history_frames(spec.history_frames, "history_frames")
    size = spec.input_size
    if size is not None and (
        len(size) != 2 or not all(type(side) is int and side > 0 for side in size)
    ):
        raise ValueError(f"input_size must be (height, width) in pixels, got {size!r}")


def model_facts(spec: ModelSpec) -> ModelFacts:
    """The facts of the tracker ``spec`` describes (see the module docstring).

    Raises:
        ValueError: bad values in the spec (`check_spec`).
        FileNotFoundError: neither a file nor a known name, or weights that cannot be had.
        CheckpointError: the file is not a checkpoint taptr loads.
    """
    check_spec(spec)
    found = checkpoint_facts(spec.checkpoint)
    config = found.config
    if spec.engine != "torch":
        from taptr.api.graph_predictor import check_exportable

        check_exportable(spec, found)  # refused by the driver, before any actor starts
    if spec.history_frames is not None and config.version != 3:
        raise ValueError("history_frames applies to TAPTRv3 models only")  # as the runner says
    points = config.context_points if spec.context_points is None else spec.context_points
    threshold = config.visibility_threshold if found.threshold is None else found.threshold
    return ModelFacts(
        source=found.name,
        checkpoint_path=found.path,
        config=config,
        visibility_threshold=threshold,
        input_size=tuple(spec.input_size or config.input_size),  # type: ignore[arg-type]
        context_points=points,
        support_points=spec.support,
        history_frames=spec.history_frames,
        weight_bytes=parameter_bytes(config),
    )


def parameter_bytes(config: ModelConfig) -> int:
    """Bytes of the parameters of the model ``config`` describes, counted on the meta device."""
    import torch

    from taptr.model.build import build_model

    with torch.device("meta"):
        model = build_model(config)
    return sum(p.numel() * p.element_size() for p in model.parameters())
