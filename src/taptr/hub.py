"""Named models: bundled weights, presets, and local checkpoint files.

``resolve_model(name_or_path)`` accepts a path to a checkpoint, the name of weights that
ship inside the package, or a preset name (freshly initialised, untrained weights, with a
warning). Nothing is ever downloaded here.
"""

from __future__ import annotations

import logging
import os
from importlib import resources
from pathlib import Path

from taptr.checkpoint import load_checkpoint
from taptr.config import PRESETS
from taptr.model.build import build_model
from taptr.model.taptr import TAPTR

logger = logging.getLogger(__name__)

BUNDLED = {"taptr-small-synthetic": ("taptr-small-synthetic.pth", "small")}
"""Weights inside the package: name → (file under ``taptr/weights``, preset it was trained as)."""

DEFAULT_MODEL = "taptr-small-synthetic"


def bundled_path(name: str) -> Path | None:
    """The file of bundled weights ``name``, or None when it is not installed."""
    filename = BUNDLED[name][0]
    path = Path(str(resources.files("taptr").joinpath("weights", filename)))
    return path if path.is_file() else None


def known_names() -> list[str]:
    """Every name `resolve_model` accepts besides paths."""
    return [*BUNDLED, *PRESETS]


def resolve_model(name_or_path: str | os.PathLike[str] | None = None) -> TAPTR:
    """Loads a model by path or name, in eval mode on the CPU.

    Args:
        name_or_path: a checkpoint file, a bundled weights name, a preset name (untrained)
            or None for the default bundled model.

    Raises:
        FileNotFoundError: neither an existing file nor a known name; lists the names.
    """
    name = DEFAULT_MODEL if name_or_path is None else str(name_or_path)
    if Path(name).is_file():
        return load_checkpoint(name)
    if name in BUNDLED:
        path = bundled_path(name)
        if path is not None:
            return load_checkpoint(path)
        preset = BUNDLED[name][1] if BUNDLED[name][1] in PRESETS else "tiny"
        logger.warning(
            "bundled weights %r are not installed: using the %r preset with UNTRAINED weights, "
            "whose tracks are meaningless",
            name,
            preset,
        )
        return build_model(preset).eval()
    if name in PRESETS:
        logger.warning("preset %r has UNTRAINED weights: its tracks are meaningless", name)
        return build_model(name).eval()
    raise FileNotFoundError(
        f"no checkpoint file or model named {name!r}; known names: {', '.join(known_names())}"
    )
