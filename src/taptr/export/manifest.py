"""The description written next to TAPTR v1 and v2's graphs: what they expect, the window rules.

An export folder holds three graphs (`GRAPHS`) and ``taptr-export.json``; a loop in any
language needs nothing else. The file is read and written with the standard library only
(`taptr.onnx.manifest_file`), so a program that only reads the manifest does not need
torch, and checked whole when read (`manifest_fields`): every key present and no other,
each value's type and range. TAPTRv3's manifest is `taptr.onnx.v3_manifest`'s.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

from taptr.onnx.manifest_file import MANIFEST_NAME as MANIFEST_NAME
from taptr.onnx.manifest_file import manifest_path, read_manifest, write_manifest
from taptr.onnx.manifest_schema import (
    Check,
    ManifestError,
    boolean,
    checked,
    choice,
    integer,
    sequence,
)

ExportFormat = Literal["onnx", "torchscript"]

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
        """Reads and checks ``taptr-export.json`` from ``directory``.

        Raises:
            FileNotFoundError: no manifest there (not an export folder).
            ManifestError: a TAPTRv3 export's manifest, or one that does not hold what a
                TAPTR v1 or v2 manifest holds (one line naming the file and the key).
        """
        data = read_manifest(directory)
        where = str(manifest_path(directory))
        if data.get("version") == 3:
            raise ManifestError(
                f"{directory} holds a TAPTRv3 export: run it with taptr.onnx.OnnxTracker "
                "(or read its manifest with taptr.onnx.V3Manifest)"
            )
        return cls(**checked(data, manifest_fields(), where))


def manifest_fields() -> dict[str, Check]:
    """Every key of a TAPTR v1 or v2 manifest (``taptr_export`` read before) and its check."""
    pair = sequence(integer(1, 8192), length=2)
    return {
        "format": choice("onnx", "torchscript"),
        "input_size": pair,
        "spatial_shapes": sequence(pair, most=8),
        "d_model": integer(4, 4096),
        "window_size": integer(1, 64),
        "window_stride": integer(1, 64),
        "long_video_frames": integer(1, 10**6),
        "memory_efficient": boolean,
        "version": choice(1, 2),
        "opset": _optional(integer(7, 100)),
    }


def _optional(check: Check) -> Check:
    def optional(value: object, key: str) -> object:
        return None if value is None else check(value, key)

    return optional
