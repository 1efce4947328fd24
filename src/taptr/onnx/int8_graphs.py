"""Int8 graphs of an export, made once with onnxruntime's static quantisation and kept.

`int8_files` returns the graph files an engine opens for ``precision="int8"``: the graphs
in `QUANTISED` replaced by quantised copies in ``<export>/int8/``, the others the export's
own. The copies are QDQ graphs (each quantised product between QuantizeLinear and
DequantizeLinear nodes): onnxruntime fuses them into int8 kernels and OpenVINO reads them
as its own int8 model, so one set of files serves both engines.

- What is quantised: the encoder's convolutions (the backbone) and matrix products (the
  deformable encoder's projections and FFNs), weights per output channel, activations per
  tensor (unsigned, asymmetric: ReLU outputs keep their whole range). The encoder is most
  of a frame's work; the decoder step stays float32 (docs/EXPORT.md measures both).
- Calibration: activation ranges (min-max) measured on frames made here
  (`taptr.onnx.calibration_frames`), never on user data or bundled photographs.
- The cache: ``int8/int8.json`` records the digest of each float32 graph it was made
  from and how; files are written atomically and the record last, so a stale or
  half-made folder is made again, never read. One line is printed when graphs are made.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import sys
from pathlib import Path
from typing import Any

from taptr.io.atomic import atomic_path
from taptr.messages import install_line
from taptr.onnx.calibration_frames import calibration_frames
from taptr.onnx.export_files import read_bounded, require_regular
from taptr.onnx.v3_manifest import V3Manifest
from taptr.onnx.v3_tensors import FILES, GRAPHS

QUANTISED = ("encoder",)
"""The graphs replaced by int8 copies."""

FOLDER = "int8"
"""The int8 graphs' folder inside an export folder."""

RECORD = "int8.json"
"""The record of what the int8 graphs were made from, inside `FOLDER`."""

CALIBRATION_FRAMES = 8
"""Frames whose activations set the ranges: two 4-frame clips; more changed no range by
more than a few percent on the exports measured, and each costs a float32 encoder run."""

RECIPE = {
    "format": "QDQ",
    "ops": ["Conv", "MatMul", "Gemm"],
    "weights": "int8 per channel, symmetric",
    "activations": "uint8 per tensor, min-max",
    "frames": CALIBRATION_FRAMES,
    "products after a Concat": "float32",
    "version": 2,
}
"""How the graphs are made; a change makes every cached folder again."""


def _digest(path: Path) -> str:
    """The SHA-256 of a file, read in blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _wanted(directory: Path, manifest: V3Manifest) -> dict[str, Any]:
    """The record the int8 folder must hold to be used: sources' digests and the recipe."""
    sources = {
        name: _digest(require_regular(manifest.graph_path(directory, name), f"graph {name}"))
        for name in QUANTISED
    }
    return {"sources": sources, "recipe": RECIPE}


def _cached(folder: Path, wanted: dict[str, Any]) -> bool:
    """Whether ``folder`` holds int8 graphs made from these sources by this recipe."""
    try:
        found = json.loads(read_bounded(folder / RECORD, 64 * 1024, "int8 record"))
    except (FileNotFoundError, ValueError):
        return False
    present = all((folder / FILES[name]).is_file() for name in QUANTISED)
    return present and found == wanted


def int8_files(directory: str | os.PathLike[str], manifest: V3Manifest) -> dict[str, str]:
    """Each graph's file for ``precision="int8"``, the int8 ones made first when missing.

    Args:
        directory: the export folder (the int8 folder is made inside it).
        manifest: its manifest.

    Raises:
        ModuleNotFoundError: onnxruntime (which quantises) is missing.
        ValueError: a graph that is not a regular file.
    """
    directory = Path(directory)
    folder = directory / FOLDER
    wanted = _wanted(directory, manifest)
    if not _cached(folder, wanted):
        for name in QUANTISED:
            quantise(manifest.graph_path(directory, name), folder / FILES[name], manifest)
        with atomic_path(folder / RECORD) as path:
            path.write_text(json.dumps(wanted, indent=1))
        # seconds to minutes of work, once per export: said, so a slow first open is explained
        made = f"made int8 {', '.join(QUANTISED)} in {folder}"
        print(f"{made} (calibrated on {CALIBRATION_FRAMES} synthetic frames)", file=sys.stderr)  # noqa: T201
    files = {name: str(manifest.graph_path(directory, name)) for name in GRAPHS}
    files.update({name: str(folder / FILES[name]) for name in QUANTISED})
    return files


class _Frames:
    """onnxruntime's calibration reader over `calibration_frames`, one frame per batch."""

    def __init__(self, manifest: V3Manifest) -> None:
        frames = calibration_frames(CALIBRATION_FRAMES, tuple(manifest.input_size))
        self.batches = iter([{"frames": frame[None]} for frame in frames])

    def get_next(self) -> dict[str, Any] | None:
        return next(self.batches, None)

    def rewind(self) -> None:  # one pass is all min-max needs
        pass


def _fed_by_concat(source: Path) -> list[str]:
    """The products whose input is a Concat's output, left float32.

    OpenVINO's int8 transformations move a quantisation step up through a Concat onto
    each of its inputs, and fail to compile the product after it when the Concat joins
    tokens (the encoder's feature levels): one product per graph, kept float32.
    """
    import onnx

    graph = onnx.load(str(source), load_external_data=False).graph
    concats = {out for node in graph.node if node.op_type == "Concat" for out in node.output}
    return [
        node.name
        for node in graph.node
        if node.op_type in RECIPE["ops"] and any(name in concats for name in node.input)
    ]


def quantise(source: Path, target: Path, manifest: V3Manifest) -> None:
    """The encoder graph at ``source`` quantised to int8 (QDQ) at ``target``, atomically.

    Raises:
        ModuleNotFoundError: onnxruntime is missing.
    """
    try:
        from onnxruntime import quantization
    except ImportError:
        raise ModuleNotFoundError(
            f"int8 graphs need onnxruntime: {install_line('export')}"
        ) from None
    target.parent.mkdir(parents=True, exist_ok=True)
    previous = logging.root.manager.disable
    # onnxruntime logs advice (pre-processing) on the root logger: not the user's concern
    logging.disable(logging.WARNING)
    try:
        with atomic_path(target) as path:
            _quantise_static(quantization, source, path, manifest)
    finally:
        logging.disable(previous)


def _quantise_static(quantization: Any, source: Path, path: Path, manifest: V3Manifest) -> None:
    """Onnxruntime's static quantisation of ``source`` into ``path`` by `RECIPE`."""
    quantization.quantize_static(
        str(source),
        str(path),
        _Frames(manifest),
        quant_format=quantization.QuantFormat.QDQ,
        op_types_to_quantize=RECIPE["ops"],
        per_channel=True,
        activation_type=quantization.QuantType.QUInt8,
        weight_type=quantization.QuantType.QInt8,
        calibrate_method=quantization.CalibrationMethod.MinMax,
        nodes_to_exclude=_fed_by_concat(source),
        # ranges folded in every 3 frames: a large encoder's every activation held for
        # all 8 frames would take gigabytes (a multiple of the frame count leaves
        # onnxruntime's last fold empty, which it reports as no data)
        extra_options={
            "WeightSymmetric": True,
            "ActivationSymmetric": False,
            "CalibMaxIntermediateOutputs": 3,
        },
        calibration_providers=["CPUExecutionProvider"],
    )
