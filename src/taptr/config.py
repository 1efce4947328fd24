"""Model hyperparameters as frozen dataclasses, with named presets.

The builder (`taptr.model.build.build_model`) is the only reader of these objects; the
modules themselves take plain typed arguments. `taptrv2` is the paper's model exactly as
the authors' released code builds it (40,040,803 parameters); `taptrv3` and `taptrv3_r50`
are the two released TAPTRv3 models (24,385,932 and 37,411,212 parameters); `tiny` and
`tiny_v3` keep the architectures with small widths and a light backbone so that tests
run in seconds.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

BackboneKind = Literal["resnet50", "resnet18", "convnet"]
CrossAttentionKind = Literal["key_aware", "standard"]
ResizeKind = Literal["lanczos", "bilinear"]
SupportKind = Literal["random", "local_and_grid", "grid", "none"]

RESNET50_CHANNELS = (256, 512, 1024, 2048)
RESNET18_CHANNELS = (64, 128, 256, 512)
RESNET_CHANNELS = {"resnet50": RESNET50_CHANNELS, "resnet18": RESNET18_CHANNELS}
SUPPORT_KINDS: tuple[str, ...] = get_args(SupportKind)
"""The support schemes by name (`SupportKind`'s), for checks and choices."""

MAX_WIDTH = 4096
"""Largest channel count (d_model, backbone widths); the paper uses 256 and 2048."""

INT_RANGES: dict[str, tuple[int, int]] = {
    "d_model": (4, MAX_WIDTH),
    "num_heads": (1, 64),
    "ffn_dim": (1, 4 * MAX_WIDTH),
    "encoder_layers": (0, 32),
    "decoder_layers": (0, 32),  # at least one: checked below with its own message
    "encoder_points": (1, 64),
    "decoder_points": (1, 64),
    "version": (1, 3),
    "window_size": (1, 64),
    "window_stride": (1, 64),
    "long_video_frames": (1, 1_000_000),
    "context_points": (0, 10_000),
    "context_patch": (1, 9),
    "history_frames": (0, 1_000_000),
}
"""Documented range [low, high] of every integer field of `ModelConfig`.

A checkpoint's config is checked against these before any module is built, so a crafted
file cannot ask for a multi-gigabyte model; every preset lies well inside them.
"""

FLOAT_RANGES: dict[str, tuple[float, float]] = {
    "sine_temperature": (1e-6, 1e6),
    "window_dropout": (0.0, 0.999),
    "visibility_threshold": (1e-6, 1 - 1e-6),
}
"""Documented range [low, high] of every float field of `ModelConfig`."""

BOOL_FIELDS = (
    "position_update",
    "disentangler",
    "cost_volume",
    "temporal_attention",
    "point_attention",
    "memory_efficient",
    "context_attention",
    "visibility_weights",
)

INPUT_SIZE_RANGE = (16, 4096)
"""Range of each of the model input's height and width."""


def check_history_frames(history_frames: object, name: str = "history_frames") -> int:
    """The TAPTRv3 history limit the rule allows: 0 (every frame) or at least 2 frames.

    One held frame would be the current one alone, which the long-temporal attention
    reads anyway; the rule is checked here for every reader of a limit (the config, the
    predictor, the export and the command line, which passes its flag as ``name``).

    Raises:
        ValueError: not a whole number, below 0, or 1.
    """
    if isinstance(history_frames, bool) or not isinstance(history_frames, int):
        raise ValueError(f"{name} must be a whole number, got {history_frames!r}")
    if history_frames < 0 or history_frames == 1:
        raise ValueError(f"{name} must be 0 (the whole video) or at least 2, got {history_frames}")
    return history_frames


def _check_int(name: str, value: Any, low: int, high: int) -> None:
    # bool is an int subclass, but True is never meant as a width or a depth
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ValueError(
            f"model config {name} must be an integer in [{low}, {high}], got {value!r:.40}"
        )


def _check_fields(
    config: Any,
    ints: dict[str, tuple[int, int]],
    floats: dict[str, tuple[float, float]],
    bools: tuple[str, ...],
) -> None:
    """Type and range of each listed field, with an error naming the first bad one."""
    for name, (low, high) in ints.items():
        if hasattr(config, name):
            _check_int(name, getattr(config, name), low, high)
    for name, (low_f, high_f) in floats.items():
        value = getattr(config, name)
        if (
            isinstance(value, bool)
            or not isinstance(value, (int, float))
            or not low_f <= value <= high_f
        ):
            raise ValueError(
                f"model config {name} must be a number in [{low_f}, {high_f}], got {value!r:.40}"
            )
    for name in bools:
        if not isinstance(getattr(config, name), bool):
            raise ValueError(
                f"model config {name} must be true or false, got {getattr(config, name)!r:.40}"
            )


def _check_size(size: Any) -> None:
    if not isinstance(size, (tuple, list)) or len(size) != 2:
        raise ValueError(f"model config input_size must be (height, width), got {size!r:.40}")
    for side in size:
        _check_int("input_size", side, *INPUT_SIZE_RANGE)


@dataclass(frozen=True)
class BackboneConfig:
    """Feature extractor returning four maps at strides 4, 8, 16 and 32.

    Attributes:
        kind: ``"resnet50"`` (torchvision ResNet-50 with frozen batch norm, TAPTRv2 and the
            larger TAPTRv3), ``"resnet18"`` (ResNet-18, the smaller TAPTRv3) or
            ``"convnet"`` (a small stack of strided convolutions with group norm, for tests
            and CPU-sized models).
        channels: output channels of the four levels. Fixed for the ResNets
            ((256, 512, 1024, 2048) and (64, 128, 256, 512)); free for ``convnet``.
    """

    kind: BackboneKind = "resnet50"
    channels: tuple[int, int, int, int] = RESNET50_CHANNELS

    def __post_init__(self) -> None:
        if self.kind not in ("resnet50", "resnet18", "convnet"):
            raise ValueError(
                f"unknown backbone kind {self.kind!r}; use 'resnet50', 'resnet18' or 'convnet'"
            )
        if not isinstance(self.channels, (tuple, list)) or len(self.channels) != 4:
            raise ValueError(f"backbone needs 4 level widths, got {self.channels!r:.60}")
        for width in self.channels:
            _check_int("backbone.channels", width, 1, MAX_WIDTH)
        fixed = RESNET_CHANNELS.get(self.kind)
        if fixed is not None and tuple(self.channels) != fixed:
            raise ValueError(f"{self.kind} has fixed widths {fixed}, got {self.channels}")


@dataclass(frozen=True)
class ModelConfig:
    """Hyperparameters of a TAPTR model (defaults are TAPTRv2's, the paper's).

    Attributes:
        backbone: the feature extractor.
        d_model: channels C of every transformer token.
        num_heads: attention heads M (deformable and multi-head attention).
        ffn_dim: hidden width of the encoder and decoder feed-forward blocks.
        encoder_layers: deformable encoder layers over each frame.
        decoder_layers: decoder layers per window (the paper's depth ablation uses 2-6).
        encoder_points: sampling points P per head and level in the encoder.
        decoder_points: sampling points P per head and level in the decoder cross-attention.
        sine_temperature: temperature of both sine position encodings (the official code
            uses 10, not the usual 10000).
        cross_attention: ``"key_aware"`` (the paper: weights from query·sampled-key dot
            products) or ``"standard"`` (learned attention weights, Table 3 ablation).
        position_update: the Attention-based Position Update (APU) inside cross-attention,
            with per-layer re-embedding of the updated position and the update-aware fusion
            of features fed to the heads. Off = Table 3 ablation.
        disentangler: the MLP that turns cross-attention logits into position-update
            weights. Off = the update reuses the content attention weights (averaged over
            heads), Table 3 ablation.
        version: decoder generation. 2: cross-attention first in each layer, the content
            updater from layer 1 on. 1 (TAPTR): temporal attention, point attention, then
            cross-attention in each layer, the content updater at every layer. 3
            (TAPTRv3): each frame decoded once, starting from the point's initial content;
            long-temporal attention over the point's past frames first in each layer, then
            cross-attention, point attention and the FFN (`taptr.model.v3`).
        cost_volume: TAPTR v1's correlation of each point with its frame, sampled around the
            point and fused into the content at every layer (version 1 only).
        temporal_attention: attention across each point's frames in a window (TAPTR v1
            Table 1 ablation when off); in version 3 the long-temporal attention over the
            point's past frames, which it always has.
        point_attention: attention among the points of each frame (Table 1 ablation).
        memory_efficient: TAPTR v1's memory-efficient mode: every point's initial content
            is sampled from frame min(start, 7), which changes outputs when a point starts
            after frame 7 (version 1 only; off reproduces the official evaluation).
        window_size: frames per sliding window.
        window_stride: frames between window starts.
        long_video_frames: at inference, videos longer than this copy the content to future
            frames only after every ⌊T / long_video_frames⌋-th window (official eval rule).
        window_dropout: dropout on the between-window content update (training only).
        input_size: (height, width) the predictor resizes videos to before the model.
        resize: how the predictor resizes frames to ``input_size``: ``"lanczos"`` (the
            official demo's mediapy resize, Pillow's Lanczos on float frames, not clipped)
            or ``"bilinear"`` (antialiased bilinear, what taptr's own models are trained on).
        context_points: the number of points the model was trained and evaluated with. The
            predictor adds seeded context points to the user's queries up to this count
            (TAPTRv2-SPEC §6: points attend to each other in every decoder layer, so a
            handful of points alone is out of the training distribution); 0 adds none.
            Read with ``support_points="random"`` only.
        support_points: how the predictor surrounds the user's points (`taptr.api.context_points`):
            ``"random"`` pads to ``context_points`` seeded random points (TAPTRv2's
            evaluation and demo); ``"local_and_grid"`` adds 63 static points around each
            query and a 6 × 6 grid (TAPTRv3's evaluation); ``"grid"`` the grid only;
            ``"none"`` nothing (taptr's own small TAPTRv3, measured as good without).
        context_attention: TAPTRv3's context-aware cross-attention: each sampling location
            is scored by comparing the 3 × 3 patch of keys around it with the point's
            initial 3 × 3 patch (version 3 only; off = the v2 key-aware dot product).
        context_patch: side K of those square patches, one feature pixel apart (odd).
        visibility_weights: TAPTRv3's long-temporal attention weighs each past frame by
            how visible the point was there (version 3 only; off = a plain mask of the
            frames since the point's start).
        history_frames: the most frames the long-temporal attention holds per point, the
            current one included, oldest dropped first (the official
            ``streaming_limited_size_of_placeholder``); 0 holds the whole clip (version 3).
        visibility_threshold: a point is reported visible where sigmoid(visibility logit)
            exceeds this (0.5 for TAPTRv2, 0.45 in TAPTRv3's evaluation).
    """

    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    d_model: int = 256
    num_heads: int = 8
    ffn_dim: int = 2048
    encoder_layers: int = 2
    decoder_layers: int = 5
    encoder_points: int = 4
    decoder_points: int = 4
    sine_temperature: float = 10.0
    cross_attention: CrossAttentionKind = "key_aware"
    position_update: bool = True
    disentangler: bool = True
    version: int = 2
    cost_volume: bool = False
    temporal_attention: bool = True
    point_attention: bool = True
    memory_efficient: bool = False
    window_size: int = 8
    window_stride: int = 4
    long_video_frames: int = 24
    window_dropout: float = 0.6
    input_size: tuple[int, int] = (512, 512)
    resize: ResizeKind = "lanczos"
    context_points: int = 800
    support_points: SupportKind = "random"
    context_attention: bool = False
    context_patch: int = 3
    visibility_weights: bool = False
    history_frames: int = 0
    visibility_threshold: float = 0.5

    def __post_init__(self) -> None:
        _check_fields(self, INT_RANGES, FLOAT_RANGES, BOOL_FIELDS)
        _check_size(self.input_size)
        if self.d_model % self.num_heads:
            raise ValueError(f"d_model {self.d_model} is not divisible by {self.num_heads} heads")
        if self.d_model % 4:
            raise ValueError(
                "d_model must be divisible by 4 (sine embeddings of 2-d and 4-d points)"
            )
        if self.cross_attention not in ("key_aware", "standard"):
            raise ValueError(f"unknown cross_attention {self.cross_attention!r}")
        if self.disentangler and not self.position_update:
            raise ValueError("disentangler=True needs position_update=True")
        if self.version not in (1, 2, 3):
            raise ValueError(
                f"version must be 1 (TAPTR), 2 (TAPTRv2) or 3 (TAPTRv3), got {self.version}"
            )
        if self.version == 1 and (self.position_update or self.cross_attention != "standard"):
            raise ValueError("version 1 uses standard cross-attention and no position update")
        if self.version != 1 and (self.cost_volume or self.memory_efficient):
            raise ValueError("cost_volume and memory_efficient exist in version 1 (TAPTR) only")
        self._check_v3()
        if not 1 <= self.window_stride <= self.window_size:
            raise ValueError("need 1 <= window_stride <= window_size")
        if self.decoder_layers < 1 or self.encoder_layers < 0:
            raise ValueError("need at least one decoder layer and a non-negative encoder depth")
        if self.resize not in ("lanczos", "bilinear"):
            raise ValueError(f"unknown resize {self.resize!r}; use 'lanczos' or 'bilinear'")
        if not isinstance(self.context_points, int) or self.context_points < 0:
            raise ValueError(
                f"context_points must be a whole number >= 0, got {self.context_points}"
            )
        if self.support_points not in SUPPORT_KINDS:
            raise ValueError(
                f"unknown support_points {self.support_points!r:.40}; use one of "
                + ", ".join(SUPPORT_KINDS)
            )

    def _check_v3(self) -> None:
        """TAPTRv3's fields: set only in version 3, and what version 3 requires."""
        if self.version != 3:
            if self.context_attention or self.visibility_weights or self.history_frames:
                raise ValueError(
                    "context_attention, visibility_weights and history_frames exist in "
                    "version 3 (TAPTRv3) only"
                )
            return
        if (self.window_size, self.window_stride) != (1, 1):
            raise ValueError("version 3 decodes frame by frame: window_size = window_stride = 1")
        if self.cross_attention != "key_aware" or not self.position_update:
            raise ValueError("version 3 uses key-aware cross-attention and the position update")
        if not self.temporal_attention:
            raise ValueError("version 3 always has its long-temporal attention")
        if self.context_patch % 2 == 0:
            raise ValueError(f"context_patch must be odd, got {self.context_patch}")
        check_history_frames(self.history_frames)

    @property
    def num_levels(self) -> int:
        """Feature levels L: the backbone's four stages (no extra stride-64 level)."""
        return len(self.backbone.channels)

    def replace(self, **changes: Any) -> ModelConfig:
        """Returns a copy with some fields changed (``backbone`` may be given as a dict)."""
        if isinstance(changes.get("backbone"), dict):
            changes["backbone"] = BackboneConfig(**_tuples(changes["backbone"]))
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (lists, numbers, strings), safe for ``torch.save`` and JSON."""
        return _lists(dataclasses.asdict(self))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ModelConfig:
        """Inverse of `to_dict`; unknown keys are an error naming them."""
        if not isinstance(data, dict):
            raise ValueError(f"model config must be a mapping, got {type(data).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(map(str, set(data) - known))
        if unknown:
            raise ValueError(f"unknown model config keys: {', '.join(unknown)}")
        values = _tuples(dict(data))
        # files written before these fields existed were run without context points and
        # with the bilinear resize
        values.setdefault("context_points", 0)
        values.setdefault("resize", "bilinear")
        if "backbone" in values:
            values["backbone"] = _backbone_from_dict(values["backbone"])
        return cls(**values)


def _backbone_from_dict(data: Any) -> BackboneConfig:
    """`BackboneConfig` from plain data; unknown keys and wrong types name the key."""
    if not isinstance(data, dict):
        raise ValueError(f"model config backbone must be a mapping, got {type(data).__name__}")
    unknown = sorted(map(str, set(data) - {f.name for f in dataclasses.fields(BackboneConfig)}))
    if unknown:
        raise ValueError(f"unknown backbone config keys: {', '.join(unknown)}")
    return BackboneConfig(**_tuples(dict(data)))


def _lists(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _lists(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_lists(v) for v in value]
    return value


def _tuples(data: dict[str, Any]) -> dict[str, Any]:
    return {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}


def taptrv2() -> ModelConfig:
    """The paper's TAPTRv2 (ResNet-50, 2 encoder and 5 decoder layers, C = 256)."""
    return ModelConfig()


def taptrv1() -> ModelConfig:
    """TAPTR (v1): 6 decoder layers, plain cross-attention last, the cost volume."""
    return ModelConfig(
        version=1,
        decoder_layers=6,
        cross_attention="standard",
        position_update=False,
        disentangler=False,
        cost_volume=True,
    )


def tiny() -> ModelConfig:
    """Same architecture with small widths and a light backbone, for fast tests."""
    return ModelConfig(
        backbone=BackboneConfig(kind="convnet", channels=(16, 24, 32, 48)),
        d_model=32,
        num_heads=4,
        ffn_dim=64,
        encoder_points=2,
        decoder_points=2,
        input_size=(64, 64),
        resize="bilinear",
        context_points=0,
    )


def small() -> ModelConfig:
    """A CPU-sized model (the bundled weights): light backbone, C = 64, 128×128 input.

    Same architecture as the paper's (2 encoder and 5 decoder layers, key-aware attention,
    position update); one training step on a 16-frame clip takes about 2.6 s on one core.
    """
    return ModelConfig(
        backbone=BackboneConfig(kind="convnet", channels=(32, 48, 64, 96)),
        d_model=64,
        num_heads=4,
        ffn_dim=256,
        input_size=(128, 128),
        resize="bilinear",
        context_points=128,
    )


def taptrv3() -> ModelConfig:
    """TAPTRv3 as released with ResNet-18 at 384 × 512 (H × W), the authors' default.

    4 decoder layers of long-temporal attention, context-aware cross-attention with the
    position update, point attention and FFN; each frame decoded once. The predictor feeds
    it as the official evaluation does: support points around each query and a grid, and
    visibility above 0.45.
    """
    return ModelConfig(
        backbone=BackboneConfig(kind="resnet18", channels=RESNET18_CHANNELS),
        decoder_layers=4,
        version=3,
        window_size=1,
        window_stride=1,
        window_dropout=0.0,
        input_size=(384, 512),
        resize="bilinear",
        context_points=0,
        support_points="local_and_grid",
        context_attention=True,
        visibility_weights=True,
        visibility_threshold=0.45,
    )


def taptrv3_r50() -> ModelConfig:
    """TAPTRv3 as released with ResNet-50 at 512 × 512."""
    return taptrv3().replace(
        backbone=BackboneConfig(kind="resnet50", channels=RESNET50_CHANNELS), input_size=(512, 512)
    )


def tiny_v3() -> ModelConfig:
    """TAPTRv3's architecture with small widths and a light backbone, for fast tests."""
    return taptrv3().replace(
        backbone=BackboneConfig(kind="convnet", channels=(16, 24, 32, 48)),
        d_model=32,
        num_heads=4,
        ffn_dim=64,
        decoder_layers=2,
        encoder_points=2,
        decoder_points=2,
        input_size=(48, 64),
        support_points="grid",
    )


PRESETS = {
    "taptrv2": taptrv2,
    "taptrv1": taptrv1,
    "taptrv3": taptrv3,
    "taptrv3-r50": taptrv3_r50,
    "tiny": tiny,
    "tiny-v3": tiny_v3,
    "small": small,
}


def get_config(name: str) -> ModelConfig:
    """Returns the preset called ``name``.

    Raises:
        KeyError: with the list of known presets.
    """
    try:
        return PRESETS[name]()
    except KeyError:
        raise KeyError(f"unknown preset {name!r}; known presets: {', '.join(PRESETS)}") from None
