"""The contract of a TAPTRv3 export: every rule of the frame loop, checked when read.

A TAPTRv3 export folder holds three ONNX graphs (`taptr.onnx.v3_tensors.GRAPHS`) and
``taptr-export.json``, read and written here with the standard library only (no torch, no
numpy), so that a loop in any language needs nothing else: the input size and how frames
are resized and normalised, each graph's inputs and outputs with their symbolic shapes,
the history rule, the logits of frames the model does not write, the support points and
the visibility threshold. docs/EXPORT.md walks through the loop; `taptr.onnx.frame_loop`
is that loop.

A folder is copied between machines and edited by hand, so `V3Manifest.load` checks the
whole manifest against its version before anything uses it (`manifest_fields`): every
key present and no other, each value's type and range, sizes bounded, the graphs' tensors
those of the model's sizes and the file names the ones an export writes. Each error is
one line naming ``taptr-export.json`` and the key.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from taptr.onnx.manifest_file import manifest_path, read_manifest, write_manifest
from taptr.onnx.manifest_schema import (
    Check,
    ManifestError,
    boolean,
    checked,
    choice,
    integer,
    real,
    record,
    refuse,
    sequence,
    text,
)
from taptr.onnx.v3_tensors import FILES, GRAPHS, TensorSpec, graph_specs
from taptr.task.resizing import RESIZE_METHODS
from taptr.task.support_schemes import SCHEMES

MAX_SIDE = 8192
"""Largest frame side or memory level side a manifest may name."""
MAX_CHANNELS = 4096
"""Largest C (`taptr.config.MAX_WIDTH`)."""
MAX_PATTERN = 4096
"""Most local offsets or grid points a support pattern may list (the official: 63, 36)."""
MAX_FRAME = 1_000_000
"""Largest frame index or history limit a manifest may name."""


@dataclass(frozen=True)
class SupportRule:
    """The points the model sees around the user's, never returned.

    Attributes:
        scheme: a registered scheme (`taptr.task.support_schemes`): ``local_and_grid``
            (the local pattern around each query, then the grid), ``grid``, ``none``, or
            ``random`` (TAPTRv2's seeded context points, which the torch-free loop does
            not draw).
        local_budget: with ``local_and_grid``, queries get their local points only while
            each with its local points stays within it: 64 · N ≤ ``local_budget``
            (32 queries); more get the grid alone.
        local_offsets: (63, 2) normalised (dx, dy) of the local pattern, added to a
            query's normalised position (float32 values); each starts on its query's frame.
        grid_positions: (36, 2) normalised (x, y) of the grid points.
        grid_start_frames: (36,) the grid points' start frames.
        context_points: ``random``: the points the query set is padded to.
    """

    scheme: str
    local_budget: int
    local_offsets: tuple[tuple[float, float], ...]
    grid_positions: tuple[tuple[float, float], ...]
    grid_start_frames: tuple[int, ...]
    context_points: int = 0


@dataclass(frozen=True)
class V3Manifest:
    """What a TAPTRv3 export folder holds and the rules of the loop that drives it.

    Attributes:
        format: ``"onnx"``.
        opset: ONNX opset of the graphs.
        input_size: (H, W) of the frames the encoder takes, RGB in [0, 1].
        resize: how frames of another size are brought to ``input_size``:
            ``"bilinear"`` (antialiased, half-pixel centres) or ``"lanczos"`` (Pillow's
            Lanczos on float frames in 0..255, not clipped).
        mean: ImageNet mean, applied inside the encoder graph (for reference).
        std: ImageNet standard deviation, applied inside the encoder graph.
        spatial_shapes: (H_l, W_l) of the memory levels; S = Σ H_l · W_l.
        d_model: channels C.
        context_patch: side K of each point's context (0: no context inputs or outputs).
        num_layers: decoder layers (inside ``decode_step``; for reference).
        visibility_threshold: visible where sigmoid(visibility logit) exceeds it.
        visibility_weights: whether frames the model does not write are "visible" on the
            point's start frame and "occluded" elsewhere (True), or carry the point's
            start label on every frame (False).
        visible_logits: the (3,) logits of a "visible" unwritten frame.
        occluded_logits: the (3,) logits of an "occluded" one.
        position_eps: the clamp of a query's position logit: log(max(p, ε) / max(1 − p, ε)).
        history_frames: the most frames held per point, the current one included, oldest
            dropped first; 0 holds every frame. A loop may take another limit (≥ 2).
        support: `SupportRule`.
        graphs: per graph, ``inputs`` and ``outputs`` (`graph_specs`).
        version: the model generation, 3.
    """

    format: str
    opset: int
    input_size: tuple[int, int]
    resize: str
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    spatial_shapes: tuple[tuple[int, int], ...]
    d_model: int
    context_patch: int
    num_layers: int
    visibility_threshold: float
    visibility_weights: bool
    visible_logits: tuple[float, float, float]
    occluded_logits: tuple[float, float, float]
    position_eps: float
    history_frames: int
    support: SupportRule
    graphs: dict[str, dict[str, tuple[TensorSpec, ...]]] = field(default_factory=dict)
    version: int = 3

    @property
    def num_tokens(self) -> int:
        """Tokens S per frame, all levels."""
        return sum(h * w for h, w in self.spatial_shapes)

    def graph_path(self, directory: str | os.PathLike[str], name: str) -> Path:
        """The file of graph ``name`` (one of `GRAPHS`) inside ``directory``."""
        if name not in GRAPHS:
            raise KeyError(f"unknown graph {name!r}; graphs: {', '.join(GRAPHS)}")
        return Path(directory) / FILES[name]

    def input_names(self, name: str) -> list[str]:
        """Graph ``name``'s input names, in call order."""
        return [spec.name for spec in self.graphs[name]["inputs"]]

    def output_names(self, name: str) -> list[str]:
        """Graph ``name``'s output names, in order."""
        return [spec.name for spec in self.graphs[name]["outputs"]]

    def save(self, directory: str | os.PathLike[str]) -> Path:
        """Writes ``taptr-export.json`` into ``directory`` (atomically, never through a link)."""
        fields = {**asdict(self), "files": dict(FILES)}
        return write_manifest(directory, fields, indent=1)

    @classmethod
    def load(cls, directory: str | os.PathLike[str]) -> V3Manifest:
        """Reads and checks ``taptr-export.json`` of a TAPTRv3 export in ``directory``.

        Raises:
            FileNotFoundError: no manifest there (not an export folder).
            ManifestError: a manifest of another model, or one that does not hold what a
                TAPTRv3 manifest holds (module docstring); one line naming file and key.
        """
        data = read_manifest(directory)
        where = str(manifest_path(directory))
        if data.get("version") != 3:
            shown = str(data.get("version"))[:20]
            raise ManifestError(
                f"{where} holds a TAPTR v{shown} export, not TAPTRv3's: load it with "
                "taptr.export.load_steps"
            )
        values = checked(data, manifest_fields(), where)
        values.pop("files")
        values["support"] = SupportRule(**values["support"])
        values["graphs"] = _graphs(values, where)
        return cls(**values)


def _pair(low: int, high: int) -> Check:
    return sequence(integer(low, high), length=2)


def _triple() -> Check:
    return sequence(real(), length=3)


def _support_fields() -> dict[str, Check]:
    point = sequence(real(-MAX_SIDE, MAX_SIDE), length=2)
    return {
        "scheme": choice(*SCHEMES),
        "local_budget": integer(0, 10**7),
        "local_offsets": sequence(point, most=MAX_PATTERN),
        "grid_positions": sequence(point, most=MAX_PATTERN),
        "grid_start_frames": sequence(integer(0, MAX_FRAME), most=MAX_PATTERN),
        "context_points": integer(0, 10**6),
    }


def _tensor(value: Any, key: str) -> dict[str, Any]:
    size = integer(0, 10**9)
    label = text(16)

    def dimension(entry: Any, where: str) -> int | str:
        return label(entry, where) if isinstance(entry, str) else size(entry, where)

    return record(
        {
            "name": text(64),
            "dtype": choice("float32", "int64", "bool"),
            "shape": sequence(dimension, most=8),
        }
    )(value, key)


def manifest_fields() -> dict[str, Check]:
    """Every key of a TAPTRv3 manifest (``taptr_export`` read before) and its check."""
    graph = record({"inputs": sequence(_tensor, most=32), "outputs": sequence(_tensor, most=32)})
    return {
        "format": choice("onnx"),
        "opset": integer(7, 100),
        "input_size": _pair(1, MAX_SIDE),
        "resize": choice(*RESIZE_METHODS),
        "mean": _triple(),
        "std": sequence(real(0, 1e3, strict=True), length=3),
        "spatial_shapes": sequence(_pair(1, MAX_SIDE), most=8),
        "d_model": integer(4, MAX_CHANNELS),
        "context_patch": integer(0, 15),
        "num_layers": integer(1, 32),
        "visibility_threshold": real(0, 1, strict=True),
        "visibility_weights": boolean,
        "visible_logits": _triple(),
        "occluded_logits": _triple(),
        "position_eps": real(0, 0.5, strict=True),
        "history_frames": integer(0, MAX_FRAME),
        "support": record(_support_fields()),
        "graphs": record(dict.fromkeys(GRAPHS, graph)),
        "version": choice(3),
        "files": record({name: choice(file) for name, file in FILES.items()}),
    }


def _graphs(values: dict[str, Any], where: str) -> dict[str, dict[str, tuple[TensorSpec, ...]]]:
    """The checked ``graphs`` as specs, refused unless they are the model's sizes'.

    Raises:
        ManifestError: a history limit of 1, a grid whose start frames do not match its
            points, no memory levels, or tensors other than those of ``graph_specs``.
    """
    if values["history_frames"] == 1:
        raise refuse(where, "history_frames", "must be 0 (every frame) or at least 2, got 1")
    support = values["support"]
    if len(support.grid_start_frames) != len(support.grid_positions):
        raise refuse(where, "support.grid_start_frames", "must hold one frame per grid point")
    if not values["spatial_shapes"]:
        raise refuse(where, "spatial_shapes", "must list at least one memory level")
    tokens = sum(h * w for h, w in values["spatial_shapes"])
    sizes = (tokens, values["d_model"], values["context_patch"], values["input_size"])
    expected = graph_specs(*sizes)
    read = {
        name: {side: tuple(TensorSpec(**spec) for spec in specs) for side, specs in graph.items()}
        for name, graph in values["graphs"].items()
    }
    for name in GRAPHS:
        for side in ("inputs", "outputs"):
            if read[name][side] != expected[name][side]:
                raise refuse(
                    where,
                    f"graphs.{name}.{side}",
                    "does not describe this model's graph (names, types or sizes differ "
                    "from its input size, memory levels, d_model and context_patch)",
                )
    return read
