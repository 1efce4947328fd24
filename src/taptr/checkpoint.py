"""Reading and writing checkpoints, safely and strictly.

Files are always read with ``torch.load(weights_only=True)``. The authors' released file
pickles an ``argparse.Namespace`` (its training arguments), which is allow-listed; any
other Python object in a file is reported by name and never unpickled.

taptr's own format is a dict ``{"format": "taptr", "version": 1, "config": <ModelConfig as
plain data>, "model": <state dict>, "ema": <state dict, optional>}``; training checkpoints
add more entries next to these. Inference uses ``ema`` when present. An optional
``"visibility_threshold"`` (a float in (0, 1), written by ``taptr calibrate``) is the threshold
`taptr.Predictor.from_pretrained` uses for the file when none is passed.
"""

from __future__ import annotations

import argparse
import os
import pickle
import pickletools
import warnings
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from taptr.config import ModelConfig, taptrv1, taptrv2
from taptr.convert.official import (
    ConversionError,
    convert_state_dict,
    looks_official,
    official_version,
    official_weights,
)
from taptr.files import atomic_path
from taptr.model.build import build_model
from taptr.model.taptr import TAPTR

FORMAT = "taptr"
VERSION = 1
SAFE_GLOBALS: list[Any] = [argparse.Namespace]


class CheckpointError(ValueError):
    """A checkpoint file cannot be used; the message names the file and the reason."""


class UnsafeCheckpointError(CheckpointError):
    """A checkpoint contains Python objects other than tensors and plain data."""


def read_file(path: str | os.PathLike[str]) -> Any:
    """Loads a file with ``weights_only=True``, allowing only ``argparse.Namespace`` extra.

    Raises:
        FileNotFoundError: the path does not exist.
        UnsafeCheckpointError: the file pickles other Python objects (they are named).
        CheckpointError: the file is not a readable PyTorch checkpoint.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        with warnings.catch_warnings(), torch.serialization.safe_globals(SAFE_GLOBALS):
            warnings.simplefilter("ignore", UserWarning)
            return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as error:
        unsafe = _unsafe_globals(path)
        if unsafe:
            raise UnsafeCheckpointError(
                f"refusing to load {path}: it contains Python objects that could run code when "
                f"unpickled ({', '.join(unsafe)}); only tensors, plain data and argparse.Namespace "
                "are accepted"
            ) from None
        raise CheckpointError(
            f"cannot read {path}: not a PyTorch checkpoint ({_short_reason(error)})"
        ) from None
    except Exception as error:
        raise CheckpointError(
            f"{path} is not a PyTorch checkpoint or is corrupt ({_short_reason(error)})"
        ) from None


def _short_reason(error: BaseException) -> str:
    """The informative line of PyTorch's long weights-only error messages."""
    text = str(error)
    marker = "WeightsUnpickler error:"
    if marker in text:
        return "weights-only unpickler: " + text.split(marker, 1)[1].strip().splitlines()[0]
    return text.strip().splitlines()[0] if text.strip() else type(error).__name__


def _unsafe_globals(path: Path) -> list[str]:
    """Names of the Python globals a file would import, other than the allowed ones."""
    allowed = {f"{g.__module__}.{g.__qualname__}" for g in SAFE_GLOBALS}
    if zipfile.is_zipfile(path):
        found = torch.serialization.get_unsafe_globals_in_checkpoint(path)
    else:
        found = _raw_pickle_globals(path)
    return [name for name in found if name not in allowed]


def _raw_pickle_globals(path: Path) -> list[str]:
    """Globals named by a plain pickle stream, read without executing it."""
    found: list[str] = []
    strings: list[str] = []
    try:
        with path.open("rb") as stream:
            for opcode, arg, _ in pickletools.genops(stream):
                if opcode.name in ("GLOBAL", "INST"):
                    found.append(str(arg).replace(" ", "."))
                elif opcode.name == "STACK_GLOBAL" and len(strings) >= 2:
                    found.append(f"{strings[-2]}.{strings[-1]}")
                elif isinstance(arg, str):
                    strings.append(arg)
    except Exception:
        pass
    return [name for name in found if not name.startswith(("torch.", "collections.OrderedDict"))]


def check_weights(model: nn.Module, state_dict: Mapping[str, Tensor], source: str) -> None:
    """Raises `CheckpointError` listing missing, unexpected and mis-shaped keys, if any."""
    expected = model.state_dict()
    missing = [k for k in expected if k not in state_dict]
    unexpected = [k for k in state_dict if k not in expected]
    misshaped = [
        f"{k}: checkpoint {list(state_dict[k].shape)} vs model {list(expected[k].shape)}"
        for k in state_dict
        if k in expected and tuple(state_dict[k].shape) != tuple(expected[k].shape)
    ]
    if not (missing or unexpected or misshaped):
        return
    lines = [f"{source} does not match the model:"]
    for title, keys in (
        ("missing", missing),
        ("unexpected", unexpected),
        ("wrong shape", misshaped),
    ):
        if keys:
            shown = keys[:10] + ([f"... {len(keys) - 10} more"] if len(keys) > 10 else [])
            lines.append(f"  {title} ({len(keys)}): " + ", ".join(shown))
    raise CheckpointError("\n".join(lines))


def load_weights(model: nn.Module, state_dict: Mapping[str, Tensor], source: str) -> None:
    """Strict load with a readable report instead of PyTorch's."""
    check_weights(model, state_dict, source)
    model.load_state_dict(dict(state_dict), strict=True)


def model_from_checkpoint(
    checkpoint: Mapping[str, Any], source: str
) -> tuple[TAPTR, dict[str, Tensor]]:
    """Builds the model a loaded checkpoint describes and returns it with its weights.

    Args:
        checkpoint: the object read from the file.
        source: the file name, for messages.
    """
    if checkpoint.get("format") == FORMAT:
        if checkpoint.get("version") != VERSION:
            raise CheckpointError(
                f"{source}: unsupported taptr checkpoint version {checkpoint.get('version')}"
            )
        config = ModelConfig.from_dict(checkpoint["config"])
        weights = checkpoint.get("ema") or checkpoint["model"]
        return build_model(config), dict(weights)
    if looks_official(checkpoint):
        try:
            converted, _ = convert_state_dict(official_weights(checkpoint))
        except ConversionError as error:
            raise CheckpointError(f"{source}: {error}") from None
        config = taptrv1() if official_version(converted) == 1 else taptrv2()
        return build_model(config), converted
    raise CheckpointError(
        f"{source} is neither a taptr checkpoint (no 'format': 'taptr' entry) nor an official "
        f"TAPTR release (no 'ema_model' / 'model' weights with official key names); "
        f"top-level keys: {', '.join(map(str, list(checkpoint)[:10])) or 'none'}"
    )


def load_checkpoint(path: str | os.PathLike[str], *, device: str | torch.device = "cpu") -> TAPTR:
    """Loads a taptr or official checkpoint into a ready model in eval mode.

    Args:
        path: a taptr checkpoint (inference or training; EMA weights when present) or the
            authors' released file, converted on the fly.
        device: where to put the model.
    """
    checkpoint = read_file(path)
    if not isinstance(checkpoint, Mapping):
        raise CheckpointError(f"{path} holds a {type(checkpoint).__name__}, not a checkpoint dict")
    model, weights = model_from_checkpoint(checkpoint, str(path))
    load_weights(model, weights, str(path))
    return model.to(device).eval()


def checkpoint_dict(
    model: TAPTR,
    ema: Mapping[str, Tensor] | None = None,
    *,
    visibility_threshold: float | None = None,
) -> dict[str, Any]:
    """Taptr's format for ``model`` (and optional EMA weights), ready for ``torch.save``.

    Args:
        model: the model (its ``config`` is stored with the weights).
        ema: optional EMA weights, stored under ``ema``.
        visibility_threshold: optional calibrated threshold in (0, 1), stored under
            ``visibility_threshold``.
    """
    if model.config is None:
        raise ValueError("the model has no config; build it with taptr.build_model")
    data: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "config": model.config.to_dict(),
        "model": {k: v.detach().cpu() for k, v in model.state_dict().items()},
    }
    if ema is not None:
        data["ema"] = {k: v.detach().cpu() for k, v in ema.items()}
    if visibility_threshold is not None:
        if not 0 < visibility_threshold < 1:
            raise ValueError(f"visibility_threshold must lie in (0, 1), got {visibility_threshold}")
        data["visibility_threshold"] = float(visibility_threshold)
    return data


def read_visibility_threshold(path: str | os.PathLike[str]) -> float | None:
    """The calibrated visibility threshold stored in a checkpoint file, or None.

    Only taptr-format files can hold one; the authors' release never does.
    """
    checkpoint = read_file(path)
    if not isinstance(checkpoint, Mapping) or checkpoint.get("format") != FORMAT:
        return None
    value = checkpoint.get("visibility_threshold")
    return None if value is None else float(value)


def save_checkpoint(
    model: TAPTR,
    path: str | os.PathLike[str],
    *,
    ema: Mapping[str, Tensor] | None = None,
    half: bool = False,
    visibility_threshold: float | None = None,
) -> Path:
    """Writes ``model`` in taptr's format, atomically.

    Args:
        model: the model (its ``config`` is stored with the weights).
        path: destination file.
        ema: optional EMA weights, stored under ``ema`` and preferred at load time.
        half: store floating tensors as float16 (half the size; loading casts back).
        visibility_threshold: optional calibrated threshold in (0, 1) stored with the weights.
    """
    data = checkpoint_dict(model, ema, visibility_threshold=visibility_threshold)
    if half:
        for key in ("model", "ema"):
            if key in data:
                data[key] = {
                    k: v.half() if v.is_floating_point() else v for k, v in data[key].items()
                }
    with atomic_path(path) as tmp:
        torch.save(data, tmp)
    return Path(path)
