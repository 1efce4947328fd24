"""onnxruntime for every exported model: the import, and the options of every session.

Imports no torch: the TAPTRv3 loop that runs the graphs without torch builds its sessions
here too (`taptr.export.v3_sessions`), as does the TAPTR v1/v2 backend
(`taptr.export.backends`).
"""

from __future__ import annotations

from types import ModuleType
from typing import Any


def onnxruntime_module() -> ModuleType:
    """``onnxruntime``, imported.

    Raises:
        ModuleNotFoundError: it is not installed (the message names the extra).
    """
    try:
        import onnxruntime
    except ImportError:
        raise ModuleNotFoundError(
            "running ONNX graphs needs onnxruntime: pip install 'taptr[export]'"
        ) from None
    return onnxruntime


def session_options(threads: int | None) -> Any:
    """Onnxruntime's options: every graph optimisation, ``threads`` intra-op threads.

    Denormal floats are flushed to zero, as taptr's PyTorch inference on a CPU does
    (`taptr.runtime.denormals`).

    Args:
        threads: intra-op threads (None: onnxruntime's default, one per core).
    """
    onnxruntime = onnxruntime_module()
    options = onnxruntime.SessionOptions()
    options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.add_session_config_entry("session.set_denormal_as_zero", "1")
    if threads is not None:
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
    return options


def open_sessions(
    graphs: dict[str, str],
    threads: int | None = None,
    providers: list[Any] | None = None,
) -> dict[str, Any]:
    """One onnxruntime session per graph, with `session_options`.

    Args:
        graphs: graph name → its ``.onnx`` file.
        threads: intra-op threads per session (None: onnxruntime's default).
        providers: execution providers (default: the CPU provider).

    Raises:
        ModuleNotFoundError: onnxruntime is missing.
    """
    onnxruntime = onnxruntime_module()
    options = session_options(threads)
    chosen = providers or ["CPUExecutionProvider"]
    return {
        name: onnxruntime.InferenceSession(path, options, providers=chosen)
        for name, path in graphs.items()
    }
