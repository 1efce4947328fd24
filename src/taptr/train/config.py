"""Training configuration as frozen dataclasses, with presets and file/CLI overrides.

`TrainConfig` holds the model (`taptr.config.ModelConfig`), the data (`DataConfig`) and
the optimisation recipe; its defaults are the official TAPTRv2 recipe (spec §1.3, §5.4)
expressed in optimizer steps. A config file (TOML or JSON) and ``key=value`` overrides
change a preset::

    preset = "small"            # the TrainConfig preset to start from (default: taptrv2)
    steps = 4000
    [model]                     # ModelConfig fields; "preset" picks a model preset first
    d_model = 64
    [data]
    root = "data/synthetic/train"

The resolved config a run writes (``config.json``) is itself a valid config file.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from taptr import config as model_presets
from taptr.config import ModelConfig

Precision = Literal["fp32", "bf16", "fp16"]

INIT_PARTS = (
    "backbone",
    "input_projections",
    "encoder",
    "query_init",
    "decoder",
    "window_updater",
)
"""The parts of a `taptr.model.taptr.TAPTR` that ``init_parts`` can copy from a checkpoint."""


@dataclass(frozen=True)
class DataConfig:
    """Training and held-out data, point sampling and augmentation (spec §5.2).

    Attributes:
        root: folder of Kubric-layout training sequences (`taptr.data.kubric`).
        extra_roots: more folders of training sequences, mixed with ``root``'s into one
            list that clips are drawn from (e.g. procedural and photo-textured videos).
        val_root: folder of held-out sequences; empty: no periodic evaluation.
        val_videos: held-out videos used per evaluation (the first ones, in order).
        frame_size: (height, width) frames are resized to when read, before augmentation.
        clip_frames: frames T per training clip, a random run of consecutive frames of the
            sequence; 0: the whole sequence (official: all 24 Kubric frames).
        num_points: trajectories N per clip, drawn among points visible on the first or
            middle frame; clips with fewer are replaced by another clip.
        eraser_prob: per-frame probability of pasting mean-colour rectangles (occluders).
        replace_prob: per-frame probability of pasting rectangles from other frames.
        colour_prob: probability of colour-jittering a clip.
        blur_prob: probability of blurring a clip.
        camera_panning: simulate camera zoom and pan by a drifting scale and crop; off:
            frames are only resized to the model's input size.
        hflip_prob: probability of mirroring a clip left-right.
        vflip_prob: probability of mirroring a clip upside-down.
        restart_fraction: share of points whose query moves to a random visible frame.
        bgr: feed frames in BGR order like the official training loader (spec §5.1;
            almost certainly a bug there, since evaluation feeds RGB).
        num_workers: data-loading processes per training process (0: in the main one).
    """

    root: str = ""
    extra_roots: tuple[str, ...] = ()
    val_root: str = ""
    val_videos: int = 16
    frame_size: tuple[int, int] = (512, 512)
    clip_frames: int = 0
    num_points: int = 800
    eraser_prob: float = 0.5
    replace_prob: float = 0.5
    colour_prob: float = 0.25
    blur_prob: float = 0.25
    camera_panning: bool = True
    hflip_prob: float = 0.5
    vflip_prob: float = 0.5
    restart_fraction: float = 0.25
    bgr: bool = False
    num_workers: int = 2


@dataclass(frozen=True)
class TrainConfig:
    """A training run. Steps count optimizer updates (each of ``grad_accum`` micro-batches).

    Attributes:
        model: the network.
        data: the data pipeline.
        out_dir: run folder (config, checkpoints, TensorBoard logs).
        steps: optimizer steps of the whole run.
        batch_size: clips per micro-batch and process.
        grad_accum: micro-batches per optimizer step.
        lr: learning rate of everything but the backbone.
        lr_backbone: learning rate of the backbone.
        weight_decay: AdamW weight decay of both groups.
        clip_norm: largest global gradient norm (0: no clipping).
        lr_milestones: optimizer steps after which the learning rates are multiplied by
            ``lr_gamma``.
        lr_gamma: the factor of each drop.
        ema_decay: EMA decay per micro-batch (the official EMA is updated after every
            micro-batch); the EMA weights are the ones checkpoints give to inference.
        precision: ``fp32``, or autocast in ``bf16`` / ``fp16`` (fp16 with loss scaling).
        visibility_weight: weight of the last layer's focal visibility loss.
        position_weight: weight of every L1 position loss.
        supervise_updated_positions: also supervise every layer's position-update output.
        supervise_occluded_positions: the position losses also count occluded entries
            (TAPTRv2); off, visible ones only (TAPTRv3's ``not_track_invisible``).
        backbone_weights: ``auto`` (ImageNet ResNet-50 weights from the torchvision cache
            when present, else random), ``none``, or a path to torchvision's file.
        init_from: checkpoint whose weights start the run (a taptr checkpoint or the
            authors' release); empty: fresh weights.
        init_parts: with ``init_from``, copy only these parts of the model (names of
            `INIT_PARTS`, e.g. ``["backbone", "input_projections", "encoder"]`` to start a
            new decoder on trained features); empty: all of it.
        seed: base seed; process r uses seed + r.
        device: ``auto`` (CUDA when available), ``cpu``, or ``cuda``.
        log_every: steps between console/TensorBoard logs.
        eval_every: steps between held-out evaluations (0: never; also at the end).
        checkpoint_every: steps between checkpoints (also at the end).
    """

    model: ModelConfig = field(default_factory=model_presets.taptrv2)
    data: DataConfig = field(default_factory=DataConfig)
    out_dir: str = "runs/taptrv2"
    # 150 epochs of ~11,000 Kubric clips on 8 GPUs with 4 accumulated micro-batches
    steps: int = 51_560
    batch_size: int = 1
    grad_accum: int = 4
    lr: float = 2e-4
    lr_backbone: float = 1e-5
    weight_decay: float = 1e-4
    clip_norm: float = 0.1
    lr_milestones: tuple[int, ...] = (34_375, 44_690)  # epochs 100 and 130 of 150
    lr_gamma: float = 0.1
    ema_decay: float = 0.9997
    precision: Precision = "fp32"
    visibility_weight: float = 1.0
    position_weight: float = 5.0
    supervise_updated_positions: bool = True
    supervise_occluded_positions: bool = True
    backbone_weights: str = "auto"
    init_from: str = ""
    init_parts: tuple[str, ...] = ()
    seed: int = 42
    device: str = "auto"
    log_every: int = 50
    eval_every: int = 2000
    checkpoint_every: int = 1000

    def __post_init__(self) -> None:
        if self.steps < 1 or self.batch_size < 1 or self.grad_accum < 1:
            raise ValueError("steps, batch_size and grad_accum must be positive")
        if self.precision not in ("fp32", "bf16", "fp16"):
            raise ValueError(f"precision must be fp32, bf16 or fp16, got {self.precision!r}")
        if not 0 <= self.ema_decay < 1:
            raise ValueError(f"ema_decay must lie in [0, 1), got {self.ema_decay}")
        if self.log_every < 1 or self.checkpoint_every < 1 or self.eval_every < 0:
            raise ValueError("log_every and checkpoint_every must be >= 1, eval_every >= 0")
        unknown = sorted(set(self.init_parts) - set(INIT_PARTS))
        if unknown:
            raise ValueError(f"unknown init_parts {unknown}; choose from {', '.join(INIT_PARTS)}")
        if self.init_parts and not self.init_from:
            raise ValueError("init_parts needs init_from (the checkpoint to copy them from)")

    def to_dict(self) -> dict[str, Any]:
        """Plain data (the form ``config.json`` stores)."""
        data = dataclasses.asdict(self)
        data["model"] = self.model.to_dict()
        return json.loads(json.dumps(data))  # tuples → lists


def taptrv2() -> TrainConfig:
    """The official recipe: TAPTRv2 on Kubric MOVi-F at 512×512, 8 GPUs × 4 micro-batches."""
    return TrainConfig(data=DataConfig(root="data/kubric_movif/r512/train"))


def small() -> TrainConfig:
    """The bundled CPU model on synthetic videos (`taptr make-synthetic`), ~100 min on a core.

    16-frame clips of 128 points at 128×128, one clip per step, no accumulation; the
    backbone trains from scratch at the full learning rate.
    """
    return TrainConfig(
        model=model_presets.get_config("small"),
        data=DataConfig(
            root="data/synthetic/train",
            val_root="data/synthetic/val",
            val_videos=8,
            frame_size=(128, 128),
            clip_frames=16,
            num_points=128,
            eraser_prob=0.25,
            replace_prob=0.25,
            num_workers=1,
        ),
        out_dir="runs/small",
        steps=2400,
        grad_accum=1,
        lr=5e-4,
        lr_backbone=5e-4,
        lr_milestones=(2000,),
        ema_decay=0.995,
        log_every=20,
        eval_every=250,
        checkpoint_every=100,
    )


def taptrv3() -> TrainConfig:
    """The official TAPTRv3 recipe (ResNet-18), TAPTRv3-DELTA.md §6.

    TAPTRv2's recipe with the ResNet-18 model's 384 × 512 crops, 4 decoder layers, no
    content hand-over between frames, and positions supervised where visible.
    """
    return TrainConfig(
        model=model_presets.taptrv3(),
        data=DataConfig(root="data/kubric_movif/r512/train"),
        out_dir="runs/taptrv3",
        supervise_occluded_positions=False,
    )


def small_v3() -> TrainConfig:
    """`small`'s CPU recipe for a TAPTRv3-architecture model (light backbone, C = 64).

    Its models track without support points: trained with 128 points per clip, one scored
    within 0.3 AJ with and without them at 8, 32 and 256 queries, at a fifth to a ninetieth
    of the time (docs/RESULTS.md, "Support points for TAPTRv3's queries").
    """
    base = small()
    model = model_presets.taptrv3().replace(
        backbone=model_presets.small().backbone,
        d_model=64,
        num_heads=4,
        ffn_dim=256,
        input_size=(128, 128),
        support_points="none",
    )
    return dataclasses.replace(
        base, model=model, out_dir="runs/small_v3", supervise_occluded_positions=False
    )


PRESETS = {"taptrv2": taptrv2, "small": small, "taptrv3": taptrv3, "small_v3": small_v3}


def _coerce(name: str, value: Any, default: Any) -> Any:
    """``value`` checked against the type of the field's default (lists become tuples)."""
    if isinstance(default, bool):
        ok = isinstance(value, bool)
    elif isinstance(default, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif isinstance(default, float):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif isinstance(default, tuple):
        ok = isinstance(value, (list, tuple))
        value = tuple(value) if ok else value
    else:
        ok = isinstance(value, type(default))
    if not ok:
        raise ValueError(
            f"config key {name!r} must be of type {type(default).__name__}, got {value!r}"
        )
    return value


def _replace(obj: Any, changes: dict[str, Any], prefix: str) -> Any:
    fields = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
    unknown = sorted(set(changes) - set(fields))
    if unknown:
        raise ValueError(f"unknown config keys: {', '.join(prefix + k for k in unknown)}")
    values = {k: _coerce(prefix + k, v, fields[k]) for k, v in changes.items()}
    return dataclasses.replace(obj, **values)


def _model(base: ModelConfig, changes: dict[str, Any]) -> ModelConfig:
    changes = dict(changes)
    if "preset" in changes:
        base = model_presets.get_config(changes.pop("preset"))
    if "backbone" in changes:
        changes["backbone"] = _replace(base.backbone, dict(changes["backbone"]), "model.backbone.")
    return _replace(base, changes, "model.")


def from_dict(data: dict[str, Any]) -> TrainConfig:
    """A config from nested plain data: a ``preset`` name plus the fields to change."""
    data = dict(data)
    preset = data.pop("preset", "taptrv2")
    if preset not in PRESETS:
        raise ValueError(f"unknown training preset {preset!r}; known: {', '.join(PRESETS)}")
    config = PRESETS[preset]()
    model_changes = dict(data.pop("model", {}))
    model = _model(config.model, model_changes)
    data_config = _replace(config.data, dict(data.pop("data", {})), "data.")
    if "context_points" not in model_changes:
        # the trained model is fed at inference as its training clips fed it: with as
        # many points as a clip holds (the saved config carries the count)
        model = model.replace(context_points=data_config.num_points)
    config = _replace(config, data, "")
    return dataclasses.replace(config, model=model, data=data_config)


def parse_overrides(overrides: list[str]) -> dict[str, Any]:
    """``["steps=10", "data.root=x", "model.backbone.kind=convnet"]`` → nested dict.

    Values are read as JSON when they parse (numbers, booleans, lists), else as strings.
    """
    nested: dict[str, Any] = {}
    for item in overrides:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise ValueError(f"override {item!r} is not KEY=VALUE")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        *parents, leaf = key.split(".")
        target = nested
        for part in parents:
            target = target.setdefault(part, {})
        target[leaf] = value
    return nested


def merge(base: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """Nested plain data with ``changes`` applied over ``base`` (tables merge key by key)."""
    merged = dict(base)
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def read_config_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Nested plain data of a ``.toml`` or ``.json`` config file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"config file not found: {path}")
    if path.suffix == ".json":
        return json.loads(path.read_text())
    if path.suffix == ".toml":
        try:
            import tomllib
        except ImportError:  # Python 3.10
            raise ValueError(f"{path}: TOML configs need Python 3.11+; use JSON") from None
        return tomllib.loads(path.read_text())
    raise ValueError(f"{path}: config files must be .toml or .json")


def load_config(path: str | os.PathLike[str] | None, overrides: Sequence[str] = ()) -> TrainConfig:
    """The file's config (or the taptrv2 preset) with ``key=value`` overrides applied."""
    data = read_config_file(path) if path else {}
    return from_dict(merge(data, parse_overrides(list(overrides))))
