"""Fuzz categories of issue 51: export folders copied between machines and edited by hand.

- the manifest: keys dropped, added or given any JSON value, lists grown past any sane
  size, numbers out of range, bytes that are not UTF-8 JSON, nesting without end, a file
  far larger than a manifest; read by `taptr.onnx.V3Manifest.load`, and where it loads,
  the loop's state made for three queries (what the 10⁶ local offsets asked 3.2 GiB for);
- the graphs: a graph file that is a FIFO, a folder, a socket, a link to a device, a
  dangling link or a loop, another graph's file, or bytes that are not a graph; opened by
  every installed engine, which must answer within `tests.fuzz_hostile.HANG_SECONDS`.

The export is a small one made here without torch: the tiny model's manifest and graphs
with its tensors' names (each output an input passed through), enough to be opened.
`tests.fuzz_targets` adds these to its `CATEGORIES`.
"""

from __future__ import annotations

import json
import os
import socket
import tempfile
from collections.abc import Callable
from dataclasses import asdict
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import strategies as st

from taptr.onnx.export_files import MAX_MANIFEST_BYTES
from taptr.onnx.manifest_file import FORMAT_VERSION, MANIFEST_NAME
from taptr.onnx.v3_manifest import SupportRule, V3Manifest
from taptr.onnx.v3_tensors import FILES, GRAPHS, graph_specs
from taptr.task.support_schemes import LOCAL_SUPPORT_BUDGET, SupportPattern, choose_scheme
from tests.fuzz_hostile import _within
from tests.fuzz_options import _JSON

SHAPES = ((12, 16), (6, 8), (3, 4), (2, 2))
"""The tiny TAPTRv3's memory levels at 48 × 64."""


def tiny_manifest(channels: int = 32, patch: int = 3) -> V3Manifest:
    """The tiny TAPTRv3's manifest at 48 × 64, made without torch."""
    pattern = SupportPattern.normalised(np.float32)
    tokens = sum(h * w for h, w in SHAPES)
    return V3Manifest(
        format="onnx",
        opset=18,
        input_size=(48, 64),
        resize="bilinear",
        mean=(0.485, 0.456, 0.406),
        std=(0.229, 0.224, 0.225),
        spatial_shapes=SHAPES,
        d_model=channels,
        context_patch=patch,
        num_layers=2,
        visibility_threshold=0.45,
        visibility_weights=True,
        visible_logits=(-6.9, 6.9, -6.9),
        occluded_logits=(-6.9, -6.9, 6.9),
        position_eps=1e-3,
        history_frames=6,
        support=SupportRule(
            scheme="grid",
            local_budget=LOCAL_SUPPORT_BUDGET,
            local_offsets=tuple(map(tuple, pattern.local_offsets.tolist())),
            grid_positions=tuple(map(tuple, pattern.grid_positions.tolist())),
            grid_start_frames=tuple(pattern.grid_start_frames.tolist()),
        ),
        graphs=graph_specs(tokens, channels, patch, (48, 64)),
    )


def manifest_fields() -> dict[str, Any]:
    """The tiny manifest as its file holds it (JSON types)."""
    return json.loads(
        json.dumps(
            {"taptr_export": FORMAT_VERSION, **asdict(tiny_manifest()), "files": dict(FILES)}
        )
    )


def write_graphs(folder: Path, manifest: V3Manifest) -> None:
    """One small ONNX graph per name, with the manifest's inputs and outputs."""
    import onnx
    from onnx import TensorProto, helper

    types = {"float32": TensorProto.FLOAT, "int64": TensorProto.INT64, "bool": TensorProto.BOOL}
    for name in GRAPHS:
        specs = manifest.graphs[name]
        inputs = [
            helper.make_tensor_value_info(s.name, types[s.dtype], list(s.shape))
            for s in specs["inputs"]
        ]
        floats = [s.name for s in specs["inputs"] if s.dtype == "float32"]
        outputs, nodes = [], []
        for index, spec in enumerate(specs["outputs"]):
            source = floats[index % len(floats)]
            nodes.append(helper.make_node("Identity", [source], [spec.name]))
            outputs.append(helper.make_tensor_value_info(spec.name, TensorProto.FLOAT, None))
        graph = helper.make_graph(nodes, name, inputs, outputs)
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
        model.ir_version = 9
        onnx.save(model, str(folder / FILES[name]))


def write_export(folder: Path, fields: dict[str, Any] | bytes | None = None) -> Path:
    """A small export in ``folder``: the graphs, and a manifest of ``fields`` (or bytes)."""
    folder.mkdir(parents=True, exist_ok=True)
    write_graphs(folder, tiny_manifest())
    data = manifest_fields() if fields is None else fields
    raw = data if isinstance(data, bytes) else json.dumps(data).encode()
    (folder / MANIFEST_NAME).write_bytes(raw)
    return folder


# -- the manifest ------------------------------------------------------------------------------

_LISTS = (
    ("support", "local_offsets"),
    ("support", "grid_positions"),
    ("support", "grid_start_frames"),
    ("spatial_shapes",),
    ("graphs", "decode_step", "inputs"),
)
_NUMBERS = st.one_of(
    st.integers(-(2**63), 2**63),
    st.sampled_from([0, -1, 1, 2, 10**9, 1.5, float("nan"), float("inf"), True]),
)


def _paths(value: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key path into ``value``'s objects and lists."""
    found = [prefix] if prefix else []
    if isinstance(value, dict):
        for key, child in value.items():
            found += _paths(child, (*prefix, key))
    elif isinstance(value, list) and value and len(prefix) < 3:
        found += _paths(value[0], (*prefix, 0))
    return found


def _at(data: Any, path: tuple) -> tuple[Any, Any]:
    """(the container holding ``path``'s last step, that step)."""
    for step in path[:-1]:
        data = data[step]
    return data, path[-1]


@st.composite
def manifest_edits(draw: st.DrawFn) -> bytes:
    """The tiny manifest's bytes, edited one way (module docstring)."""
    fields = manifest_fields()
    kind = draw(st.sampled_from(["drop", "add", "retype", "grow", "number", "bytes", "nested"]))
    if kind == "bytes":
        raw = json.dumps(fields).encode()
        cut = draw(st.integers(0, len(raw)))
        return raw[:cut] + draw(st.binary(max_size=8)) + raw[cut:]
    if kind == "nested":
        depth = draw(st.integers(1, 100_000))
        return b'{"support": ' + b"[" * depth + b"]" * depth + b"}"
    path = draw(st.sampled_from(_paths(fields)))
    container, step = _at(fields, path)
    if kind == "drop" and isinstance(container, dict):
        del container[step]
    elif kind == "add" and isinstance(container, dict):
        container[draw(st.text(max_size=8))] = draw(_JSON)
    elif kind in ("retype", "drop", "add"):
        container[step] = draw(_JSON)
    elif kind == "number":
        container[step] = draw(_NUMBERS)
    else:  # grow a list past any sane size
        where, key = _at(fields, draw(st.sampled_from(_LISTS)))
        where[key] = where[key][:1] * draw(st.sampled_from([0, 2, 5000, 200_000]))
    return json.dumps(fields).encode()


def read_manifest_folder(raw: bytes) -> None:
    """Loads an export folder holding ``raw`` as its manifest; then makes the loop's state."""
    from taptr.onnx.frame_loop import add_points, start_state
    from taptr.onnx.graph_memory import check_run_memory
    from taptr.onnx.video_tracker import support_pattern

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        (folder / MANIFEST_NAME).write_bytes(raw)
        manifest = V3Manifest.load(folder)
    pattern = support_pattern(manifest)
    starts, xy = np.array([0, 1, 2]), np.full((3, 2), 0.5, np.float32)
    scheme = choose_scheme(manifest.support.scheme, 3, pattern)
    support = scheme.points(starts, xy, pattern)
    check_run_memory(manifest, 3 + len(support.parents), 8, None)
    state = start_state(manifest)
    add_points(manifest, state, np.r_[starts, support.start_frames], np.r_[xy, support.positions])


def read_huge_manifest(size: int) -> None:
    """A manifest file of ``size`` bytes (sparse): refused without reading it whole."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / MANIFEST_NAME
        with open(path, "wb") as stream:
            stream.write(b'{"taptr_export": 1, "x": "')
            stream.truncate(size)
        V3Manifest.load(tmp)


huge_manifests = st.sampled_from([MAX_MANIFEST_BYTES + 1, 10**7, 2**30])
"""Sizes of manifests larger than any manifest (the 1 GB one of the issue among them)."""


# -- the graphs ----------------------------------------------------------------------------------

GRAPH_KINDS = (
    "fifo",
    "folder",
    "socket",
    "link to /dev/zero",
    "dangling link",
    "link loop",
    "another graph",
    "empty",
    "bytes",
    "truncated",
)
ENGINES = ("onnxruntime", "openvino") if find_spec("openvino") else ("onnxruntime",)

tampered_graphs = st.tuples(
    st.sampled_from(GRAPHS), st.sampled_from(GRAPH_KINDS), st.sampled_from(ENGINES), st.binary()
)
"""(graph, what its file is instead, engine, bytes for ``bytes``)."""


def _tamper(path: Path, kind: str, data: bytes, sockets: list[socket.socket]) -> list[Path]:
    """Makes the graph file at ``path`` a ``kind``; returns FIFOs a blocked open waits on."""
    graph = path.read_bytes()
    path.unlink()
    if kind == "fifo":
        os.mkfifo(path)
        return [path]
    makers: dict[str, Callable[[], Any]] = {
        "folder": path.mkdir,
        "link to /dev/zero": lambda: path.symlink_to("/dev/zero"),
        "dangling link": lambda: path.symlink_to(path.with_name("nowhere")),
        "link loop": lambda: path.symlink_to(path),
        "another graph": lambda: path.write_bytes(_other_graph(path)),
        "empty": lambda: path.write_bytes(b""),
        "bytes": lambda: path.write_bytes(data),
        "truncated": lambda: path.write_bytes(graph[: len(graph) // 2]),
    }
    if kind == "socket":
        server = socket.socket(socket.AF_UNIX)
        server.bind(str(path))
        sockets.append(server)
    else:
        makers[kind]()
    return []


def _other_graph(path: Path) -> bytes:
    other = next(f for f in FILES.values() if f != path.name)
    return (path.parent / other).read_bytes()


def open_tampered(value: tuple[str, str, str, bytes]) -> None:
    """Opens an export whose graph ``name`` is tampered with; a blocked open is a failure."""
    from taptr.onnx.graph_engines import open_graphs

    name, kind, engine, data = value
    with tempfile.TemporaryDirectory(dir="/tmp") as tmp:
        folder = write_export(Path(tmp) / "export")
        sockets: list[socket.socket] = []
        fifos = _tamper(folder / FILES[name], kind, data, sockets)
        try:
            _within(lambda: open_graphs(folder, engine, threads=1), fifos)
        finally:
            for server in sockets:
                server.close()


CATEGORIES: dict[str, tuple[Any, Callable[[Any], Any]]] = {
    "export manifest, keys/types/sizes": (manifest_edits(), read_manifest_folder),
    "export manifest, far too large": (huge_manifests, read_huge_manifest),
    "export graphs, not regular files or not the graph named": (tampered_graphs, open_tampered),
}
"""The categories of this module, added to `tests.fuzz_targets.CATEGORIES`."""
