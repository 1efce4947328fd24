"""Which model a checkpoint holds, and whether it is the one its name promises.

Named weights (``taptrv3-official``, ``taptrv3-r50-official``, ``taptrv2-official``, ...)
know their architecture: a preset of `taptr.config.PRESETS`. A file found or downloaded
under such a name is compared with it before any module is built: two configs are the
same architecture when the models they describe have the same weights, names and shapes
(compared on the meta device, nothing allocated), so a calibrated threshold or another
count of context points does not matter, while TAPTRv2 weights under TAPTRv3's name, or
ResNet-50 weights under ResNet-18's, are refused with what the file holds.
"""

from __future__ import annotations

import functools
import math

import torch

from taptr.config import ModelConfig, get_config
from taptr.model.build import build_model

BACKBONE_NAMES = {
    "resnet50": "ResNet-50",
    "resnet18": "ResNet-18",
    "convnet": "small convolutional",
}
"""How a backbone kind is named in messages."""


def describe(config: ModelConfig) -> str:
    """The model a config describes, in words: ``TAPTRv3 (ResNet-18 backbone, C = 256)``."""
    generation = "TAPTR v1" if config.version == 1 else f"TAPTRv{config.version}"
    backbone = BACKBONE_NAMES.get(config.backbone.kind, config.backbone.kind)
    return f"{generation} ({backbone} backbone, C = {config.d_model})"


@functools.lru_cache(maxsize=8)
def _shapes(config: ModelConfig) -> tuple[tuple[str, tuple[int, ...]], ...]:
    """The weights of the model ``config`` describes, name and shape, built on meta."""
    with torch.device("meta"):
        state = build_model(config).state_dict()
    return tuple((key, tuple(value.shape)) for key, value in state.items())


def same_architecture(found: ModelConfig, expected: ModelConfig) -> bool:
    """Whether two configs describe models with the same weights (names and shapes)."""
    return _shapes(found) == _shapes(expected)


def architecture_problem(found: ModelConfig, name: str, preset: str) -> str | None:
    """What is wrong with a file under ``name`` that holds ``found``, or None when it fits.

    Args:
        found: the config of the file's model (its own, or inferred from an official file).
        name: the weights' name (``taptrv3-official``), for the message.
        preset: the architecture the name promises (a key of `taptr.config.PRESETS`).
    """
    expected = get_config(preset)
    if same_architecture(found, expected):
        return None
    return (
        f"holds {describe(found)}, but {name} is {describe(expected)}: it is another model's "
        f"weights under {name}'s file name; delete it and fetch {name} again, or pass the "
        "file's path to use it as what it is"
    )


def weights_bytes(config: ModelConfig, bytes_per_value: int = 4) -> int:
    """Bytes of the weights of the model ``config`` describes, at ``bytes_per_value`` each.

    A checkpoint of that model holds at least this much at its storage precision (float16
    for ``taptr convert --half``): a smaller file under its name is a truncated download.
    """
    return bytes_per_value * sum(math.prod(shape) for _, shape in _shapes(config))
