"""Starting weights of a run: ImageNet ResNet-50 when available, or any loadable checkpoint.

The official run starts from torchvision's ImageNet ResNet-50 (``IMAGENET1K_V1``, the
default of torchvision 0.14 it used). Nothing is downloaded: ``auto`` looks for the file in
torchvision's cache (where ``torchvision.models.resnet50(weights="IMAGENET1K_V1")`` puts
it) and otherwise trains the backbone from scratch, with a warning.
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch

from taptr.model.taptr import TAPTR
from taptr.weights.checkpoint import load_weights, read_checkpoint, read_file

logger = logging.getLogger(__name__)

RESNET50_IMAGENET_FILE = "resnet50-0676ba61.pth"


def cached_imagenet_weights() -> Path:
    """Where torchvision caches its ImageNet ResNet-50 weights."""
    return Path(torch.hub.get_dir()) / "checkpoints" / RESNET50_IMAGENET_FILE


def init_backbone(model: TAPTR, setting: str) -> bool:
    """Loads ImageNet weights into a ResNet-50 backbone.

    Args:
        model: the freshly built model.
        setting: ``auto`` (the torchvision cache if the file is there), ``none``, or the
            path of torchvision's ResNet-50 state dict.

    Returns:
        Whether weights were loaded.

    Raises:
        FileNotFoundError: an explicit path does not exist.
        ValueError: a path is given for a backbone that is not ResNet-50.
    """
    kind = model.config.backbone.kind if model.config else "resnet50"
    if setting == "none" or (setting == "auto" and kind != "resnet50"):
        return False
    if kind != "resnet50":
        raise ValueError(f"backbone_weights is a ResNet-50 file but the backbone is {kind!r}")
    path = cached_imagenet_weights() if setting == "auto" else Path(setting)
    if not path.is_file():
        if setting != "auto":
            raise FileNotFoundError(f"backbone weights not found: {path}")
        logger.warning(
            "ImageNet ResNet-50 weights not found at %s: training the backbone from scratch "
            "(the paper starts from ImageNet weights)",
            path,
        )
        return False
    state = read_file(path)
    # the classifier is not part of the trunk; batch norm is frozen and has no counter
    trunk = {
        k: v for k, v in state.items() if not k.startswith("fc.") and "num_batches_tracked" not in k
    }
    load_weights(model.backbone.body, trunk, str(path))
    logger.info("backbone initialised from ImageNet weights %s", path)
    return True


def init_from_checkpoint(model: TAPTR, path: str, parts: tuple[str, ...] = ()) -> None:
    """Copies the weights of any checkpoint `taptr.load_checkpoint` reads (EMA when present).

    The file's weights go straight into ``model``: no second model is built.

    Args:
        model: the freshly built model.
        path: the checkpoint.
        parts: copy only these top-level parts (e.g. ``("backbone", "encoder")``), each
            whole and strictly; the rest keeps its fresh weights. Empty: everything.

    Raises:
        taptr.weights.checkpoint.CheckpointError: the checkpoint's model (or part) does not match,
            with the missing, unexpected and mis-shaped keys listed.
    """
    _, weights = read_checkpoint(path)
    if not parts:
        load_weights(model, weights, str(path))
        logger.info("weights initialised from %s", path)
        return
    for part in parts:
        prefix = f"{part}."
        own = {k[len(prefix) :]: v for k, v in weights.items() if k.startswith(prefix)}
        load_weights(getattr(model, part), own, f"{path} ({part})")
    logger.info("%s initialised from %s", ", ".join(parts), path)
