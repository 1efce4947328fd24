"""Reading and writing checkpoints, safely and strictly.

Files are always read with ``torch.load(weights_only=True)``. The authors' released file
pickles an ``argparse.Namespace`` (its training arguments), which is allow-listed; any
other Python object in a file is reported by name and never unpickled. Before that, the file's
size and the sizes it declares are checked against what it holds and the ``checkpoint_bytes``
limit (`taptr.io.checkpoint_scan`), and a checkpoint's config and weights are validated before
any module is built, so a small crafted file cannot make taptr allocate gigabytes.

taptr's own format is a dict ``{"format": "taptr", "version": 1, "config": <ModelConfig as
plain data>, "model": <state dict>, "ema": <state dict, optional>}``; training checkpoints
add more entries next to these. Inference uses ``ema`` when present. An optional
``"visibility_threshold"`` (a float in (0, 1), written by ``taptr calibrate``) is the threshold
`taptr.Predictor.from_pretrained` uses for the file when none is passed.
"""

from __future__ import annotations

import argparse
import functools
import os
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from taptr.config import ModelConfig
from taptr.io import limits
from taptr.io.atomic import atomic_path
from taptr.io.checkpoint_scan import ScanError, scan_checkpoint
from taptr.io.file_kind import kind, require_file, shown
from taptr.io.nesting import NestingError, check_nesting
from taptr.model.build import build_model
from taptr.model.taptr import TAPTR
from taptr.official.convert import (
    ConversionError,
    convert_state_dict,
    looks_official,
    official_config,
    official_weights,
)
from taptr.weights.identity import architecture_problem
from taptr.weights.safe_checks import (
    CheckpointError,
    UnsafeCheckpointError,
    all_finite,
    config_shape_problem,
    key_name,
    named_failures,
    short_repr,
)

FORMAT = "taptr"
VERSION = 1
SAFE_GLOBALS: list[Any] = [argparse.Namespace]


def read_file(path: str | os.PathLike[str]) -> Any:
    """Loads a file with ``weights_only=True``, allowing only ``argparse.Namespace`` extra.

    Before ``torch.load``, `taptr.io.checkpoint_scan.scan_checkpoint` checks the file's size,
    the sizes its pickles declare against the data it holds (the ``checkpoint_bytes`` limit
    of `taptr.io.limits`) and the globals it names, so a small crafted file cannot make
    PyTorch allocate gigabytes.

    Raises:
        FileNotFoundError: the path does not exist.
        UnsafeCheckpointError: the file pickles other Python objects (they are named).
        CheckpointError: the path is not a regular file (a folder, FIFO or device, refused
            before opening), is a web page (a download that saved the link's page), is not a
            readable PyTorch checkpoint, declares more data than it holds, exceeds the size
            limit or nests its data too deeply; the message names the file.
    """
    path = Path(path)
    try:
        if kind(path, "checkpoint") is None:
            raise FileNotFoundError(f"checkpoint not found: {shown(path)}")
        require_file(path, "checkpoint")
    except FileNotFoundError:
        raise
    except ValueError as error:
        raise CheckpointError(str(error)) from None
    if is_web_page(path):
        raise CheckpointError(
            f"{path} is a web page (HTML), not a checkpoint: a download link saved its page "
            "instead of the file (Google Drive answers curl and wget with a confirmation page "
            "for large files); download the file in a browser"
        )
    try:
        scan = scan_checkpoint(path)
    except limits.LimitError as error:
        raise CheckpointError(str(error)) from None
    except ScanError as error:
        raise CheckpointError(f"cannot read {path}: {error}") from None
    unsafe = _unsafe(scan.globals)
    if unsafe:
        raise UnsafeCheckpointError(
            f"refusing to load {path}: it contains Python objects that could run code when "
            f"unpickled ({', '.join(unsafe)}); only tensors, plain data and argparse.Namespace "
            "are accepted"
        )
    try:
        with warnings.catch_warnings(), torch.serialization.safe_globals(SAFE_GLOBALS):
            warnings.simplefilter("ignore", UserWarning)
            loaded = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # PyTorch raises many types; none may escape unnamed
        raise CheckpointError(
            f"cannot read {path}: not a PyTorch checkpoint or corrupt ({_short_reason(error)})"
        ) from None
    try:  # every later step (messages, key names, the config) may walk it recursively
        check_nesting(loaded, str(path))
    except NestingError as error:
        raise CheckpointError(str(error)) from None
    return loaded


def is_web_page(path: Path) -> bool:
    """Whether the file starts like an HTML document (after blanks and a byte-order mark)."""
    with path.open("rb") as stream:
        head = stream.read(512).lstrip(b"\xef\xbb\xbf \t\r\n").lower()
    return head.startswith((b"<!doctype html", b"<html"))


def _unsafe(names: list[str]) -> list[str]:
    """The globals, among ``names``, that the weights-only loader would refuse."""
    try:
        from torch._weights_only_unpickler import _get_allowed_globals

        allowed = set(_get_allowed_globals())
    except (ImportError, TypeError):  # pragma: no cover - another PyTorch: torch.load decides
        return []
    allowed |= {f"{g.__module__}.{g.__qualname__}" for g in SAFE_GLOBALS}
    return list(dict.fromkeys(name for name in names if name not in allowed))


def _short_reason(error: BaseException) -> str:
    """The informative line of PyTorch's long weights-only error messages.

    PyTorch's text suggests ``weights_only=False``, which would run code from the file:
    those lines are never passed on.
    """
    text = str(error)
    marker = "WeightsUnpickler error:"
    if marker in text:
        text = text.split(marker, 1)[1]
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    advice = ("weights_only", "Weights only", "Please", "Check the documentation", "trusted")
    useful = [line for line in lines if not any(word in line for word in advice)]
    return useful[0][:300] if useful else type(error).__name__


def check_weights(model: nn.Module, state_dict: Mapping[str, Any], source: str) -> None:
    """Raises `CheckpointError` listing missing, unexpected and mismatched keys, if any.

    Every weight must be a dense tensor of the model's shape and kind (floating point where
    the model has floats, never complex), with finite values: NaN weights would give NaN
    tracks without an error. ``model`` may live on the meta device (nothing allocated).
    """
    _check_against(model.state_dict(), state_dict, source)


def _check_against(
    expected: Mapping[str, Tensor], state_dict: Mapping[str, Any], source: str
) -> None:
    """`check_weights` against the expected tensors (or meta tensors) of a model."""
    missing = [k for k in expected if k not in state_dict]
    unexpected = [k for k in state_dict if k not in expected]
    present = [k for k in state_dict if k in expected]
    tensors = [k for k in present if _dense(state_dict[k])]
    not_tensors = [f"{k}: {type(state_dict[k]).__name__}" for k in present if k not in tensors]
    misshaped_keys = {k for k in tensors if tuple(state_dict[k].shape) != tuple(expected[k].shape)}
    misshaped = [
        f"{k}: checkpoint {list(state_dict[k].shape)} vs model {list(expected[k].shape)}"
        for k in tensors
        if k in misshaped_keys
    ]
    mistyped = [
        f"{k}: checkpoint {state_dict[k].dtype} vs model {expected[k].dtype}"
        for k in tensors
        if state_dict[k].is_complex()
        or state_dict[k].is_floating_point() != expected[k].is_floating_point()
    ]
    # only weights of the model's shape: their size is the model's, never what a file's
    # view declares (a zero stride can show billions of elements of one stored number)
    non_finite = [
        k
        for k in tensors
        if k not in misshaped_keys and state_dict[k].is_floating_point()
        if not all_finite(state_dict[k])
    ]
    if not (missing or unexpected or not_tensors or misshaped or mistyped or non_finite):
        return
    lines = [f"{source} does not match the model:"]
    for title, keys in (
        ("missing", missing),
        ("unexpected", unexpected),
        ("not a dense tensor", not_tensors),
        ("wrong shape", misshaped),
        ("wrong dtype", mistyped),
        ("non-finite values (NaN or inf)", non_finite),
    ):
        if keys:
            shown = keys[:10] + ([f"... {len(keys) - 10} more"] if len(keys) > 10 else [])
            lines.append(f"  {title} ({len(keys)}): " + ", ".join(shown))
    raise CheckpointError("\n".join(lines))


def _dense(value: Any) -> bool:
    """Whether ``value`` is an ordinary tensor with data (not sparse, quantized or meta)."""
    return (
        isinstance(value, Tensor)
        and value.layout == torch.strided
        and not value.is_quantized
        and not value.is_meta
    )


def load_weights(model: nn.Module, state_dict: Mapping[str, Tensor], source: str) -> None:
    """Strict load with a readable report instead of PyTorch's."""
    check_weights(model, state_dict, source)
    model.load_state_dict(dict(state_dict), strict=True)


def _config(data: Any, source: str) -> ModelConfig:
    """The checkpoint's model config, validated (types and ranges) before any module exists.

    Its shape is bounded first (`taptr.weights.safe_checks.config_shape_problem`): the range
    checks print the values they refuse.
    """
    if not isinstance(data, Mapping):
        raise CheckpointError(f"{source}: 'config' is a {type(data).__name__}, not a mapping")
    problem = config_shape_problem(data)
    if problem:
        raise CheckpointError(f"{source}: invalid model config: {problem}")
    try:
        return ModelConfig.from_dict(dict(data))
    except (ValueError, TypeError) as error:
        raise CheckpointError(f"{source}: invalid model config: {error}") from None


def _weights(checkpoint: Mapping[str, Any], source: str) -> dict[str, Any]:
    """The EMA weights when present, else the model weights, as a name → tensor dict."""
    key = "ema" if checkpoint.get("ema") is not None else "model"
    weights = checkpoint.get(key)
    if not isinstance(weights, Mapping) or not all(isinstance(k, str) for k in weights):
        raise CheckpointError(f"{source}: '{key}' is not a dict of named weights")
    return dict(weights)


@functools.lru_cache(maxsize=4)
def _skeleton(config: ModelConfig) -> dict[str, Tensor]:
    """The meta-device state dict of the model ``config`` describes: no memory used."""
    with torch.device("meta"):
        return dict(build_model(config).state_dict())


def checkpoint_contents(
    checkpoint: Mapping[str, Any], source: str
) -> tuple[ModelConfig, dict[str, Tensor]]:
    """The model config and weights a loaded checkpoint holds, checked, with nothing built.

    The config is validated and the weights checked against the shapes and dtypes it
    implies on the meta device, so a small file cannot make anyone build a large model.
    Official releases are converted to taptr's names.

    Args:
        checkpoint: the object read from the file.
        source: the file name, for messages.

    Raises:
        CheckpointError: unknown layout, invalid config, or weights that do not match.
    """
    if isinstance(checkpoint.get("format"), str) and checkpoint["format"] == FORMAT:
        version = checkpoint.get("version")
        if type(version) is not int or version != VERSION:  # a tensor or bool is no version
            shown_version = short_repr(checkpoint.get("version"))
            raise CheckpointError(f"{source}: unsupported taptr checkpoint version {shown_version}")
        config = _config(checkpoint.get("config"), source)
        weights = _weights(checkpoint, source)
    elif looks_official(checkpoint):
        try:
            weights, _ = convert_state_dict(official_weights(checkpoint))
        except ConversionError as error:
            raise CheckpointError(f"{source}: {error}") from None
        config = official_config(weights)
    else:
        raise CheckpointError(
            f"{source} is neither a taptr checkpoint (no 'format': 'taptr' entry) nor an "
            f"official TAPTR release (no 'ema_model' / 'model' weights with official key "
            f"names); top-level keys: {', '.join(map(key_name, list(checkpoint)[:10])) or 'none'}"
        )
    _check_against(_skeleton(config), weights, source)
    return config, weights


def read_checkpoint(path: str | os.PathLike[str]) -> tuple[ModelConfig, dict[str, Tensor]]:
    """The model config and weights of a checkpoint file, checked, without building a model.

    For copying a file's weights into a model that exists already (fine-tuning).
    """
    with named_failures(path):
        return checkpoint_contents(_read_mapping(path), str(path))


def model_from_checkpoint(
    checkpoint: Mapping[str, Any], source: str
) -> tuple[TAPTR, dict[str, Tensor]]:
    """Builds the model a loaded checkpoint describes and returns it with its weights.

    Args:
        checkpoint: the object read from the file.
        source: the file name, for messages.

    Raises:
        CheckpointError: unknown layout, invalid config, or weights that do not match.
    """
    config, weights = checkpoint_contents(checkpoint, source)
    return build_model(config), weights


def load_checkpoint(path: str | os.PathLike[str], *, device: str | torch.device = "cpu") -> TAPTR:
    """Loads a taptr or official checkpoint into a ready model in eval mode.

    Args:
        path: a taptr checkpoint (inference or training; EMA weights when present) or the
            authors' released file, converted on the fly.
        device: where to put the model.

    Raises:
        FileNotFoundError: the file does not exist.
        CheckpointError: the file cannot be used (the message names it and the reason).
    """
    return load_checkpoint_and_threshold(path, device=device)[0]


def load_checkpoint_and_threshold(
    path: str | os.PathLike[str],
    *,
    device: str | torch.device = "cpu",
    expected: tuple[str, str] | None = None,
) -> tuple[TAPTR, float | None]:
    """`load_checkpoint` and `read_visibility_threshold` of one file, reading it once.

    Args:
        path: the checkpoint file.
        device: where to put the model.
        expected: for named weights, (name, preset): a file of another architecture
            is refused before any module is built (`taptr.weights.identity`).
    """
    with named_failures(path):
        checkpoint = _read_mapping(path)
        config, weights = checkpoint_contents(checkpoint, str(path))
        if expected is not None:
            check_architecture(config, path, *expected)
        model = build_model(config)
        load_weights(model, weights, str(path))
        return model.to(device).eval(), _stored_threshold(checkpoint, str(path))


def check_architecture(
    config: ModelConfig, path: str | os.PathLike[str], name: str, preset: str
) -> None:
    """Raises `CheckpointError` when a file under ``name`` holds another architecture."""
    problem = architecture_problem(config, name, preset)
    if problem is not None:
        raise CheckpointError(f"{path} {problem}")


def _read_mapping(path: str | os.PathLike[str]) -> Mapping[str, Any]:
    checkpoint = read_file(path)
    if not isinstance(checkpoint, Mapping):
        raise CheckpointError(f"{path} holds a {type(checkpoint).__name__}, not a checkpoint dict")
    return checkpoint


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
    return _stored_threshold(read_file(path), str(path))


def _stored_threshold(checkpoint: Any, source: str) -> float | None:
    if not isinstance(checkpoint, Mapping) or checkpoint.get("format") != FORMAT:
        return None
    value = checkpoint.get("visibility_threshold")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < 1:
        raise CheckpointError(
            f"{source}: visibility_threshold must be a number in (0, 1), got {short_repr(value)}"
        )
    return float(value)


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
