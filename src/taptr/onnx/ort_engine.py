"""The ``onnxruntime`` engine: exported graphs as onnxruntime sessions, numpy in and out.

`OnnxRuntimeGraphs` opens the three graphs of a TAPTRv3 export and implements
`taptr.onnx.graph_engines.StepGraphs`; `open_sessions` serves TAPTR v1 and v2's window
graphs too (`taptr.export.graph_steps`). Execution providers come as named presets
(`PRESETS`), or as onnxruntime's own list:

- ``cpu``: the CPU provider;
- ``cuda``: the CUDA provider (onnxruntime puts what it does not take on the CPU's);
- ``cuda-graphs``: the CUDA provider replaying ``decode_step`` as CUDA graphs: every input
  and output bound at a fixed device address (I/O binding), one captured graph per point
  count and history size (`BoundStep`);
- ``tensorrt``: the TensorRT provider, its engines kept in ``trt_cache`` (then CUDA's).

Precision (`taptr.onnx.precisions`): ``float32`` and ``int8`` (the export's int8 graphs);
``bfloat16`` is refused, the CPU provider has no bfloat16 kernels for these graphs.

Every session takes every graph optimisation and flushes denormal floats to zero, as the
PyTorch predictor does on a CPU (`taptr.runtime.denormals`): products of small weights
and activations otherwise take a path tens of times slower on x86 CPUs.
"""

from __future__ import annotations

import os
from types import ModuleType
from typing import Any

import numpy as np

from taptr.onnx.graph_engines import ENGINES, check_signature, engine_module
from taptr.onnx.precisions import PrecisionError, check_precision, precision_files
from taptr.onnx.v3_manifest import V3Manifest

PRESETS = ("cpu", "cuda", "cuda-graphs", "tensorrt")
"""The named provider lists."""

_NEEDED = {
    "cuda": "CUDAExecutionProvider",
    "cuda-graphs": "CUDAExecutionProvider",
    "tensorrt": "TensorrtExecutionProvider",
}


def onnxruntime_module() -> ModuleType:
    """``onnxruntime``, imported.

    Raises:
        ModuleNotFoundError: it is not installed (the message names the extra).
    """
    return engine_module(ENGINES["onnxruntime"])


def session_options(threads: int | None) -> Any:
    """Onnxruntime's options: every graph optimisation, ``threads`` intra-op threads.

    Args:
        threads: intra-op threads (None: onnxruntime's default, one per core).
    """
    onnxruntime = onnxruntime_module()
    options = onnxruntime.SessionOptions()
    options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.add_session_config_entry("session.set_denormal_as_zero", "1")
    # idle threads sleep unless the user asked OpenMP's pools to spin: spinning takes the
    # cores other work on a shared machine wanted (taptr.runtime.threads has the numbers)
    spin = os.environ.get("OMP_WAIT_POLICY", "").strip().upper() == "ACTIVE"
    options.add_session_config_entry("session.intra_op.allow_spinning", "1" if spin else "0")
    if threads is not None:
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
    return options


def preset_providers(preset: str, trt_cache: str | None = None) -> list[Any]:
    """The execution providers of a preset, in order of preference.

    onnxruntime places what no provider listed takes on its CPU provider.

    Args:
        preset: one of `PRESETS`.
        trt_cache: ``tensorrt``: where TensorRT keeps the engines it builds (default:
            none kept).

    Raises:
        ValueError: an unknown preset.
    """
    if preset not in PRESETS:
        raise ValueError(f"preset must be one of {', '.join(PRESETS)}, got {preset!r}")
    if preset == "cpu":
        return ["CPUExecutionProvider"]
    graphs = "1" if preset == "cuda-graphs" else "0"
    cuda = ("CUDAExecutionProvider", {"enable_cuda_graph": graphs})
    if preset != "tensorrt":
        return [cuda]
    options = {"trt_engine_cache_enable": "1" if trt_cache else "0"}
    if trt_cache:
        options["trt_engine_cache_path"] = trt_cache
    return [("TensorrtExecutionProvider", options), cuda]


def check_available(preset: str) -> None:
    """Refuses a preset whose provider this onnxruntime lacks.

    Raises:
        ValueError: the preset's provider is not in onnxruntime's available providers.
    """
    needed = _NEEDED.get(preset)
    if needed is not None and needed not in onnxruntime_module().get_available_providers():
        raise ValueError(
            f"the {preset!r} preset needs onnxruntime's {needed}, which this onnxruntime "
            "lacks: pip install onnxruntime-gpu (with CUDA, and TensorRT for 'tensorrt')"
        )


def open_sessions(
    graphs: dict[str, str],
    threads: int | None = None,
    providers: list[Any] | None = None,
) -> dict[str, Any]:
    """One onnxruntime session per graph, with `session_options`.

    Args:
        graphs: graph name → its ``.onnx`` file (checked to be a regular file first).
        threads: intra-op threads per session (None: onnxruntime's default).
        providers: execution providers (default: the CPU provider).

    Raises:
        ModuleNotFoundError: onnxruntime is missing.
        ValueError: a graph file that onnxruntime cannot read as a graph (one line).
    """
    onnxruntime = onnxruntime_module()
    options = session_options(threads)
    chosen = ["CPUExecutionProvider"] if providers is None else providers
    sessions = {}
    for name, path in graphs.items():
        try:
            sessions[name] = onnxruntime.InferenceSession(path, options, providers=chosen)
        except (RuntimeError, *_session_errors(onnxruntime)) as error:
            reason = " ".join(str(error).split())[:200]
            raise ValueError(f"{path}: onnxruntime cannot open it as a graph ({reason})") from None
    return sessions


def _session_errors(onnxruntime: ModuleType) -> tuple[type[Exception], ...]:
    """The exception classes of onnxruntime (``InvalidProtobuf``, ``Fail``, ...)."""
    errors = vars(onnxruntime.capi.onnxruntime_pybind11_state).values()
    return tuple(e for e in errors if isinstance(e, type) and issubclass(e, Exception))


class OnnxRuntimeGraphs:
    """The graphs of a TAPTRv3 export as onnxruntime sessions.

    Args:
        directory: the export folder.
        preset: the providers by name (`PRESETS`; default ``cpu``).
        threads: intra-op threads per session (default: onnxruntime's, one per core).
        providers: onnxruntime's provider list instead of a preset, names or
            (name, options) pairs.
        trt_cache: ``tensorrt``: where TensorRT keeps the engines it builds.
        precision: ``float32`` (the export's graphs) or ``int8`` (its int8 graphs, made
            in ``<directory>/int8/`` on first use); ``bfloat16`` is refused.

    Raises:
        ModuleNotFoundError: onnxruntime is missing.
        ValueError: a preset this onnxruntime cannot run, a precision it cannot run
            (``bfloat16``; the message names the engine that can), or an export folder that fails
            its checks (another model's, a graph that is not a regular file or not the
            graph the manifest names).
    """

    engine = "onnxruntime"

    def __init__(
        self,
        directory: str | os.PathLike[str],
        *,
        preset: str = "cpu",
        threads: int | None = None,
        providers: list[Any] | None = None,
        trt_cache: str | None = None,
        precision: str = "float32",
    ) -> None:
        onnxruntime_module()  # its message before the manifest's
        if check_precision(precision) == "bfloat16":
            raise PrecisionError(
                "the onnxruntime engine cannot run precision='bfloat16' (its CPU provider has "
                "no bfloat16 kernels for these graphs): use engine='openvino' on a CPU with "
                "AVX512-BF16 or AMX, or precision='int8'"
            )
        self.precision = precision
        chosen = preset_providers(preset, trt_cache) if providers is None else providers
        if providers is None:
            check_available(preset)
        self.manifest = V3Manifest.load(directory)
        files = precision_files(directory, self.manifest, precision)
        self.sessions = open_sessions(files, threads, chosen)
        for name, session in self.sessions.items():
            inputs = [spec.name for spec in session.get_inputs()]
            outputs = [spec.name for spec in session.get_outputs()]
            check_signature(self.manifest, name, files[name], inputs, outputs)
        self.step = BoundStep(self.sessions["decode_step"]) if preset == "cuda-graphs" else None

    def encode(self, frames: np.ndarray) -> np.ndarray:
        """Frames (F, 3, H, W) RGB in [0, 1] → memory (F, S, C)."""
        feed = {"frames": np.ascontiguousarray(frames, np.float32)}
        return self.sessions["encoder"].run(None, feed)[0]

    def start_points(
        self, memory: np.ndarray, positions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Memory (S, C), positions (N, 2) → content (N, C), context (N, K, K, C) or None."""
        feed = {"memory": memory, "positions": np.ascontiguousarray(positions, np.float32)}
        outputs = self.sessions["start_points"].run(None, feed)
        return outputs[0], (outputs[1] if len(outputs) > 1 else None)

    def decode_step(self, inputs: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
        """``decode_step``'s named inputs → new positions (N, 4), visibility (N, 3), features."""
        if self.step is not None:
            return self.step(inputs)
        return tuple(self.sessions["decode_step"].run(None, inputs))


class BoundStep:
    """``decode_step`` replayed as CUDA graphs: inputs and outputs at fixed device addresses.

    A CUDA graph replays the kernels it captured on the buffers it captured them with, so
    each shape (points N, history slots H) gets its own device buffers and its own graph
    (onnxruntime's ``gpu_graph_id``), captured on its first run; later frames of that
    shape copy their inputs into the buffers and replay. The loop's shapes change only
    when points join or leave and when the history buffer doubles.

    Args:
        session: the ``decode_step`` session, made with ``enable_cuda_graph``.
        device: where the buffers live (``cuda``; ``cpu`` for the tests, where the same
            binding runs without graphs).
    """

    def __init__(self, session: Any, device: str = "cuda") -> None:
        self.session = session
        self.device = device
        self.onnxruntime = onnxruntime_module()
        self.bound: dict[tuple[tuple[int, ...], ...], tuple[Any, dict[str, Any], Any]] = {}

    def _bind(self, inputs: dict[str, np.ndarray]) -> tuple[Any, dict[str, Any], Any]:
        """A binding, its input buffers and run options for the shapes of ``inputs``."""
        ortvalue = self.onnxruntime.OrtValue
        binding = self.session.io_binding()
        buffers = {}
        for name, value in inputs.items():
            array = np.ascontiguousarray(value)
            buffers[name] = ortvalue.ortvalue_from_numpy(array, self.device, 0)
            binding.bind_ortvalue_input(name, buffers[name])
        for output in self.session.get_outputs():
            binding.bind_output(output.name, self.device)
        options = self.onnxruntime.RunOptions()
        options.add_run_config_entry("gpu_graph_id", str(len(self.bound) + 1))
        self.session.run_with_iobinding(binding, options)  # allocates outputs, captures
        for output, value in zip(self.session.get_outputs(), binding.get_outputs(), strict=True):
            binding.bind_ortvalue_output(output.name, value)
        return binding, buffers, options

    def __call__(self, inputs: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
        """One replayed step; the outputs copied back to the host."""
        key = tuple(np.shape(value) for value in inputs.values())
        if key not in self.bound:
            self.bound[key] = self._bind(inputs)
        else:
            binding, buffers, options = self.bound[key]
            for name, value in inputs.items():
                buffers[name].update_inplace(np.ascontiguousarray(value))
            self.session.run_with_iobinding(binding, options)
        # copies: the bound outputs are overwritten by the next replay
        return tuple(np.array(value.numpy()) for value in self.bound[key][0].get_outputs())
