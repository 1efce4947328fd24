"""The contract of a TAPTRv3 export: its graphs' tensors and every rule of the frame loop.

A TAPTRv3 export folder holds three ONNX graphs (`GRAPHS`) and ``taptr-export.json``,
read and written here with the standard library only (no torch, no numpy), so that a
loop in any language needs nothing else: the input size and how frames are resized and
normalised, each graph's inputs and outputs with their symbolic shapes, the history rule,
the logits of frames the model does not write, the support points and the visibility
threshold. docs/EXPORT.md walks through the loop; `taptr.export.v3_loop` is that loop.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

from taptr.export.manifest import read_manifest, write_manifest

GRAPHS = ("encoder", "start_points", "decode_step")
"""Graph names: frames → memory; memory and positions → content and context; one frame's
decoder with its state."""

FILES = {name: f"{name}.onnx" for name in GRAPHS}


@dataclass(frozen=True)
class TensorSpec:
    """One input or output of a graph.

    Attributes:
        name: its name in the graph.
        dtype: ``float32``, ``int64`` or ``bool``.
        shape: sizes, numbers where fixed and names where dynamic (``points`` N,
            ``slots`` H of the history buffer, ``frames`` F).
    """

    name: str
    dtype: str
    shape: tuple[int | str, ...]


def graph_specs(
    tokens: int, channels: int, patch: int, input_size: tuple[int, int]
) -> dict[str, dict[str, tuple[TensorSpec, ...]]]:
    """Each graph's inputs and outputs, in call order, for the model's sizes.

    Args:
        tokens: S, memory tokens of a frame.
        channels: C.
        patch: K, side of the points' context (0: a model without it, no context tensors).
        input_size: (H, W) of the frames.
    """
    n, h = "points", "slots"
    context = (TensorSpec("context", "float32", (n, patch, patch, channels)),) if patch else ()
    memory = TensorSpec("memory", "float32", (tokens, channels))
    return {
        "encoder": {
            "inputs": (TensorSpec("frames", "float32", ("frames", 3, *input_size)),),
            "outputs": (TensorSpec("memory", "float32", ("frames", tokens, channels)),),
        },
        "start_points": {
            "inputs": (memory, TensorSpec("positions", "float32", (n, 2))),
            "outputs": (TensorSpec("content", "float32", (n, channels)), *context),
        },
        "decode_step": {
            "inputs": (
                memory,
                TensorSpec("frame", "int64", ()),
                TensorSpec("start_frames", "int64", (n,)),
                TensorSpec("initial_content", "float32", (n, channels)),
                *context,
                TensorSpec("positions", "float32", (n, 4)),
                TensorSpec("visibility", "float32", (n, 3)),
                TensorSpec("history_content", "float32", (n, h, channels)),
                TensorSpec("history_visibility", "float32", (n, h)),
                TensorSpec("slot_frames", "int64", (h,)),
                TensorSpec("slot_held", "bool", (h,)),
            ),
            "outputs": (
                TensorSpec("new_positions", "float32", (n, 4)),
                TensorSpec("new_visibility", "float32", (n, 3)),
                TensorSpec("features", "float32", (n, channels)),
            ),
        },
    }


@dataclass(frozen=True)
class SupportRule:
    """The points the model sees around the user's, never returned.

    Attributes:
        scheme: ``local_and_grid`` (the local pattern around each query, then the grid),
            ``grid``, ``none``, or ``random`` (TAPTRv2's seeded context points, which the
            torch-free loop does not draw).
        local_budget: with ``local_and_grid``, queries get their local points only while
            64 · N + 36 ≤ ``local_budget`` + 36 (32 queries); more get the grid alone.
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
        """Writes ``taptr-export.json`` into ``directory``."""
        fields = {**asdict(self), "files": {name: FILES[name] for name in GRAPHS}}
        return write_manifest(directory, fields, indent=1)

    @classmethod
    def load(cls, directory: str | os.PathLike[str]) -> V3Manifest:
        """Reads ``taptr-export.json`` of a TAPTRv3 export from ``directory``.

        Raises:
            FileNotFoundError: no manifest there (not an export folder).
            ValueError: a manifest of another format version or of another model.
        """
        data = read_manifest(directory)
        if data.get("version") != 3:
            raise ValueError(
                f"{directory} holds a TAPTR v{data.get('version')} export, not TAPTRv3's: "
                "load it with taptr.export.load_steps"
            )
        data.pop("files", None)
        for key in ("input_size", "mean", "std", "visible_logits", "occluded_logits"):
            data[key] = tuple(data[key])
        data["spatial_shapes"] = tuple(tuple(s) for s in data["spatial_shapes"])
        support = data["support"]
        for key in ("local_offsets", "grid_positions"):
            support[key] = tuple(tuple(p) for p in support[key])
        support["grid_start_frames"] = tuple(support["grid_start_frames"])
        data["support"] = SupportRule(**support)
        data["graphs"] = {
            name: {
                side: tuple(
                    TensorSpec(s["name"], s["dtype"], tuple(s["shape"])) for s in specs[side]
                )
                for side in ("inputs", "outputs")
            }
            for name, specs in data["graphs"].items()
        }
        return cls(**data)
