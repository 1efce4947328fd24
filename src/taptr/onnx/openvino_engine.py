"""The ``openvino`` engine: exported graphs compiled by OpenVINO, numpy in and out.

OpenVINO is Intel's inference engine, made for CPUs like the ones taptr's tests run on;
it reads the ONNX graphs directly. `OpenVinoGraphs` compiles the three graphs of a TAPTRv3
export for a device (``CPU`` by default) and implements
`taptr.onnx.graph_engines.StepGraphs`. The encoder is compiled for one frame at a time,
the only way the loop calls it: OpenVINO's CPU plugin chooses its kernels once for static
shapes, 15 % faster than the same graph compiled with its frame count dynamic (a call
with several frames runs them one by one). The points N and the history slots H stay
dynamic: the plugin runs a compiled graph at any size, preparing each new shape on its
first call (one to one and a half steps more; docs/EXPORT.md), where a static step would be compiled
again, seconds, for every point count and every doubling of the history.

Precision is asked, never left to the device: OpenVINO runs float32 graphs in bfloat16 on
CPUs that have it (AVX512-BF16, AMX) unless told otherwise, so ``precision="float32"``
(the default) keeps the graphs' float32; ``"bfloat16"`` asks for the faster, less exact
one and is refused on a CPU without it (OpenVINO would quietly run float32); ``"int8"``
compiles the export's int8 graphs (`taptr.onnx.int8_graphs`), their other layers in
float32. ``TAPTR_CPU`` (`taptr.cpu_levels`) takes bfloat16 away as it does for PyTorch.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from taptr.cpu_levels import VARIABLE, allowed
from taptr.onnx.graph_engines import ENGINES, check_signature, engine_module
from taptr.onnx.precisions import PrecisionError, check_precision, precision_files
from taptr.onnx.v3_manifest import V3Manifest

HINTS = {"float32": "f32", "bfloat16": "bf16", "int8": "f32"}
"""Each precision's ``INFERENCE_PRECISION_HINT``: int8 graphs keep their other layers f32."""


def compile_config(precision: str, threads: int | None, cache_dir: str | None) -> dict[str, str]:
    """OpenVINO's compile properties for one graph.

    Args:
        precision: one of `taptr.onnx.precisions.PRECISIONS`.
        threads: inference threads (None: OpenVINO's choice, one per core).
        cache_dir: where OpenVINO keeps compiled graphs between processes (None: not kept).

    Raises:
        ValueError: an unknown precision.
    """
    config = {
        "INFERENCE_PRECISION_HINT": HINTS[check_precision(precision)],
        "PERFORMANCE_HINT": "LATENCY",  # one frame at a time: one stream, every thread on it
    }
    if threads is not None:
        config["INFERENCE_NUM_THREADS"] = str(threads)
    if cache_dir is not None:
        config["CACHE_DIR"] = str(cache_dir)
    return config


class OpenVinoGraphs:
    """The graphs of a TAPTRv3 export compiled by OpenVINO.

    Args:
        directory: the export folder.
        device: OpenVINO's device (``CPU``, ``GPU``, ``AUTO``).
        precision: ``float32`` (the graphs' own), ``bfloat16`` (CPUs with AVX512-BF16 or
            AMX) or ``int8`` (the export's int8 graphs, made in ``<directory>/int8/`` on
            first use).
        threads: inference threads (default: one per core).
        cache_dir: where OpenVINO keeps compiled graphs between processes.

    Raises:
        ModuleNotFoundError: openvino is missing.
        ValueError: a precision this device cannot run (one line naming the missing CPU
            feature), an export folder that fails its checks (another model's, a graph that
            is not a regular file or not the graph the manifest names), or a graph
            OpenVINO cannot compile (one line).
    """

    engine = "openvino"

    def __init__(
        self,
        directory: str | os.PathLike[str],
        *,
        device: str = "CPU",
        precision: str = "float32",
        threads: int | None = None,
        cache_dir: str | None = None,
    ) -> None:
        openvino = engine_module(ENGINES["openvino"])
        config = compile_config(precision, threads, cache_dir)
        core = openvino.Core()
        if precision == "bfloat16":
            check_bfloat16(core, device)
        self.precision = precision
        self.manifest = V3Manifest.load(directory)
        self.requests = {}
        one_frame = {"frames": [1, 3, *self.manifest.input_size]}
        for name, path in precision_files(directory, self.manifest, precision).items():
            shapes = one_frame if name == "encoder" else None
            compiled = _compiled(openvino, core, path, (device, config), shapes)
            inputs = [port.get_any_name() for port in compiled.inputs]
            outputs = [port.get_any_name() for port in compiled.outputs]
            check_signature(self.manifest, name, path, inputs, outputs)
            self.requests[name] = compiled.create_infer_request()

    def _run(self, name: str, feed: dict[str, np.ndarray]) -> list[np.ndarray]:
        """Graph ``name`` on named inputs; its outputs in order, as arrays of their own.

        The inputs are read where they lie (the history alone is tens of megabytes at 800
        points, copied on every frame otherwise); the outputs are copies, since the loop
        keeps them past the next call.
        """
        results = self.requests[name].infer(feed, share_inputs=True)
        return [np.asarray(value) for value in results.values()]

    def encode(self, frames: np.ndarray) -> np.ndarray:
        """Frames (F, 3, H, W) RGB in [0, 1] → memory (F, S, C), one frame per call."""
        frames = np.ascontiguousarray(frames, np.float32)
        memory = [
            self._run("encoder", {"frames": frames[i : i + 1]})[0] for i in range(len(frames))
        ]
        return np.concatenate(memory) if len(memory) != 1 else memory[0]

    def start_points(
        self, memory: np.ndarray, positions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Memory (S, C), positions (N, 2) → content (N, C), context (N, K, K, C) or None."""
        feed = {"memory": memory, "positions": np.ascontiguousarray(positions, np.float32)}
        outputs = self._run("start_points", feed)
        return outputs[0], (outputs[1] if len(outputs) > 1 else None)

    def decode_step(self, inputs: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
        """``decode_step``'s named inputs → new positions (N, 4), visibility (N, 3), features."""
        return tuple(self._run("decode_step", inputs))


def check_bfloat16(core: Any, device: str) -> None:
    """Refuses bfloat16 on a CPU without bfloat16 products (or with them taken away).

    OpenVINO reports ``BF16`` among a CPU's optimisation capabilities where it has
    AVX512-BF16 or AMX; other devices (a GPU) are left to OpenVINO.

    Raises:
        ValueError: the CPU lacks both, or ``TAPTR_CPU`` takes them away (one line).
    """
    if not device.upper().startswith("CPU"):
        return
    found = "BF16" in core.get_property("CPU", "OPTIMIZATION_CAPABILITIES")
    if not found:
        raise PrecisionError(
            "precision='bfloat16' needs a CPU with AVX512-BF16 or AMX, and this CPU has "
            "neither: use precision='float32' or 'int8'"
        )
    if not allowed("avx512_bf16"):
        raise PrecisionError(
            f"precision='bfloat16' needs AVX512-BF16 or AMX, which {VARIABLE}="
            f"{os.environ.get(VARIABLE, '').strip()} takes away: use precision='float32' or 'int8'"
        )


def _compiled(
    openvino: Any,
    core: Any,
    path: str,
    target: tuple[str, dict[str, str]],
    shapes: dict[str, list[int]] | None,
) -> Any:
    """One graph read as ONNX and compiled; failures as one-line ValueErrors.

    The ONNX front end is named: left to choose, OpenVINO tries every format it reads
    (TensorFlow, PaddlePaddle, ...) on a file that is not ONNX.

    Args:
        openvino: the package.
        core: its ``Core``.
        path: the graph's file.
        target: (device, compile properties).
        shapes: inputs fixed to these shapes before compiling (None: as exported).
    """
    frontend = openvino.frontend
    failures = tuple(getattr(frontend, n) for n in dir(frontend) if n.endswith("Failure"))
    device, config = target
    try:
        onnx = frontend.FrontEndManager().load_by_framework("onnx")
        model = onnx.convert(onnx.load(path))
        if shapes is not None:
            model.reshape(shapes)
        return core.compile_model(model, device, config)
    except (RuntimeError, *failures) as error:
        reason = " ".join(str(error).split())[:240]
        raise ValueError(f"{path}: OpenVINO cannot compile it for {device} ({reason})") from None
