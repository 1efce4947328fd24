"""The description written next to exported graphs: what they expect and the window rules.

An export folder holds three graphs (`GRAPHS`) and ``taptr-export.json``; a loop in any
language needs nothing else. This module reads and writes that file with the standard
library only, so a program that only reads the manifest does not need torch.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

from taptr.io.atomic import atomic_path

ExportFormat = Literal["onnx", "torchscript"]

MANIFEST_NAME = "taptr-export.json"
FORMAT_VERSION = 1
GRAPHS = ("encoder", "init_points", "decode_window")
"""Graph names: frames → memory; memory and positions → content; one window's decoder."""

INPUT_NAMES = {
    "encoder": ("frames",),
    "init_points": ("memory", "positions"),
    "decode_window": ("memory", "content", "positions", "initial", "tracking", "update"),
}
"""Input names of each graph, in call order (shapes: `taptr.export.graph_runner.Steps`)."""

OUTPUT_NAMES = {
    "encoder": ("memory",),
    "init_points": ("content",),
    "decode_window": ("window_positions", "window_visibility_logits", "next_content"),
}

EXTENSIONS = {"onnx": ".onnx", "torchscript": ".pt"}


@dataclass(frozen=True)
class ExportManifest:
    """What a folder of exported graphs holds.

    Attributes:
        format: ``"onnx"`` or ``"torchscript"``.
        input_size: (H, W) frames must have, RGB in [0, 1], before the encoder graph.
        spatial_shapes: (H_l, W_l) of the L memory levels; S = Σ H_l·W_l.
        d_model: channels C of the memory and the content.
        window_size: frames per window.
        window_stride: frames between window starts.
        long_video_frames: videos longer than this hand the content to future frames only
            after every ⌊T / long_video_frames⌋-th window.
        memory_efficient: TAPTR v1's rule: on the first window every point takes its
            initial content from frame min(start, last frame of the window).
        version: the model generation (1: TAPTR, 2: TAPTRv2).
        opset: ONNX opset of the graphs, or None for TorchScript.
    """

    format: ExportFormat
    input_size: tuple[int, int]
    spatial_shapes: tuple[tuple[int, int], ...]
    d_model: int
    window_size: int
    window_stride: int
    long_video_frames: int
    memory_efficient: bool
    version: int
    opset: int | None = None

    @property
    def num_tokens(self) -> int:
        """Tokens S per frame, all levels."""
        return sum(h * w for h, w in self.spatial_shapes)

    def graph_path(self, directory: str | os.PathLike[str], name: str) -> Path:
        """The file of graph ``name`` (one of `GRAPHS`) inside ``directory``."""
        if name not in GRAPHS:
            raise KeyError(f"unknown graph {name!r}; graphs: {', '.join(GRAPHS)}")
        return Path(directory) / f"{name}{EXTENSIONS[self.format]}"

    def save(self, directory: str | os.PathLike[str]) -> Path:
        """Writes ``taptr-export.json`` into ``directory``."""
        return write_manifest(directory, asdict(self))

    @classmethod
    def load(cls, directory: str | os.PathLike[str]) -> ExportManifest:
        """Reads ``taptr-export.json`` from ``directory``.

        Raises:
            FileNotFoundError: no manifest there (not an export folder).
            ValueError: a manifest of another version, or of a TAPTRv3 export.
        """
        data = read_manifest(directory)
        if data.get("version") == 3:
            raise ValueError(
                f"{directory} holds a TAPTRv3 export: run it with taptr.export.OnnxTracker "
                "(or read its manifest with taptr.export.V3Manifest)"
            )
        data["input_size"] = tuple(data["input_size"])
        data["spatial_shapes"] = tuple(tuple(s) for s in data["spatial_shapes"])
        return cls(**data)


def read_manifest(directory: str | os.PathLike[str]) -> dict[str, Any]:
    """The manifest of an export folder (any model) as a dict, its format version checked.

    Raises:
        FileNotFoundError: no manifest there (not an export folder).
        ValueError: a manifest of another format version.
    """
    path = Path(directory) / MANIFEST_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{directory} is not a taptr export folder (no {MANIFEST_NAME})")
    data = json.loads(path.read_text())
    version = data.pop("taptr_export", None)
    if version != FORMAT_VERSION:
        raise ValueError(f"{path}: export format {version}, this taptr reads {FORMAT_VERSION}")
    return data


def write_manifest(
    directory: str | os.PathLike[str], fields: dict[str, Any], indent: int = 2
) -> Path:
    """Writes the manifest of an export folder (any model), whole or not at all.

    Args:
        directory: the export folder.
        fields: the manifest's fields; the format version is added first.
        indent: JSON indentation.
    """
    path = Path(directory) / MANIFEST_NAME
    data = {"taptr_export": FORMAT_VERSION, **fields}
    with atomic_path(path) as temporary:
        temporary.write_text(json.dumps(data, indent=indent) + "\n")
    return path
