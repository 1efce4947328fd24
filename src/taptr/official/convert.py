"""Converter from the authors' released checkpoints to taptr's module names.

The official files (``taptrv2.pth``, ``taptrv1.pth``, TAPTRv3's
``TAPTRv3_resnet18_384x512.pth`` and ``TAPTRv3_resnet50_512x512.pth``) are training
checkpoints of a
DINO-derived model: the weights used for inference are under ``ema_model`` with a
``module.`` prefix, the points are "boxes" and visibility is a "class". This module is the
only place where those names appear. The map is explicit: every official key must match
exactly one rule, the aliased head copies (``transformer.decoder.bbox_embed`` /
``class_embed``) are dropped after checking that they equal the canonical tensors, and
shapes are checked by the strict load.
"""

from __future__ import annotations

import re
from collections.abc import Mapping

from torch import Tensor

from taptr.config import ModelConfig, taptrv1, taptrv2, taptrv3, taptrv3_r50

# (official pattern, our replacement), applied to keys without the "module." prefix.
_DECODER_LAYER = r"transformer\.decoder\.layers\.(\d+)\."
RULES: tuple[tuple[str, str], ...] = (
    (r"backbone\.0\.body\.(.+)", r"backbone.body.\1"),
    (r"input_proj\.(\d+)\.([01])\.(weight|bias)", r"input_projections.levels.\1.\2.\3"),
    (r"transformer\.level_embed", "encoder.level_embed"),
    (
        r"transformer\.encoder\.layers\.(\d+)\.self_attn\.(\w+)\.(weight|bias)",
        r"encoder.layers.\1.attention.\2.\3",
    ),
    (
        r"transformer\.encoder\.layers\.(\d+)\.norm1\.(weight|bias)",
        r"encoder.layers.\1.norm_attention.\2",
    ),
    (
        r"transformer\.encoder\.layers\.(\d+)\.linear1\.(weight|bias)",
        r"encoder.layers.\1.ffn.layers.0.\2",
    ),
    (
        r"transformer\.encoder\.layers\.(\d+)\.linear2\.(weight|bias)",
        r"encoder.layers.\1.ffn.layers.1.\2",
    ),
    (
        r"transformer\.encoder\.layers\.(\d+)\.norm2\.(weight|bias)",
        r"encoder.layers.\1.norm_ffn.\2",
    ),
    (
        _DECODER_LAYER + r"cross_attn\.(\w+)\.(weight|bias)",
        r"decoder.layers.\1.cross_attention.\2.\3",
    ),
    (
        _DECODER_LAYER + r"cross_attn\.mlp_calulate_similarity\.0\.(weight|bias)",
        r"decoder.layers.\1.cross_attention.similarity.layers.0.\2",
    ),
    (
        _DECODER_LAYER + r"cross_attn\.mlp_calulate_similarity\.2\.(weight|bias)",
        r"decoder.layers.\1.cross_attention.similarity.layers.1.\2",
    ),
    (_DECODER_LAYER + r"norm1\.(weight|bias)", r"decoder.layers.\1.norm_cross.\2"),
    (
        _DECODER_LAYER + r"ltemp_self_attn\.(.+)",
        r"decoder.layers.\1.long_temporal.attention.\2",
    ),
    (_DECODER_LAYER + r"norm_ltemp\.(weight|bias)", r"decoder.layers.\1.norm_long_temporal.\2"),
    (
        _DECODER_LAYER + r"lta_temporal_embedding\.freqs",
        r"decoder.layers.\1.long_temporal.rotary.freqs",
    ),
    (_DECODER_LAYER + r"temp_self_attn\.(.+)", r"decoder.layers.\1.temporal_attention.\2"),
    (_DECODER_LAYER + r"norm_temp\.(weight|bias)", r"decoder.layers.\1.norm_temporal.\2"),
    (_DECODER_LAYER + r"self_attn\.(.+)", r"decoder.layers.\1.point_attention.\2"),
    (_DECODER_LAYER + r"norm2\.(weight|bias)", r"decoder.layers.\1.norm_points.\2"),
    (_DECODER_LAYER + r"linear1\.(weight|bias)", r"decoder.layers.\1.ffn.layers.0.\2"),
    (_DECODER_LAYER + r"linear2\.(weight|bias)", r"decoder.layers.\1.ffn.layers.1.\2"),
    (_DECODER_LAYER + r"norm3\.(weight|bias)", r"decoder.layers.\1.norm_ffn.\2"),
    (
        _DECODER_LAYER + r"update_pos_embed_head\.layers\.(\d)\.(weight|bias)",
        r"decoder.layers.\1.position_embed.layers.\2.\3",
    ),
    (
        _DECODER_LAYER + r"caupdate_weight_normalizer\.0\.(weight|bias)",
        r"decoder.layers.\1.position_update.disentangler.layers.0.\2",
    ),
    (
        _DECODER_LAYER + r"caupdate_weight_normalizer\.2\.(weight|bias)",
        r"decoder.layers.\1.position_update.disentangler.layers.1.\2",
    ),
    (
        _DECODER_LAYER + r"caupdate_weight_regressor\.0\.(weight|bias)",
        r"decoder.layers.\1.position_update.disentangler.layers.2.\2",
    ),
    (_DECODER_LAYER + r"corr_fuser\.0\.(weight|bias)", r"decoder.layers.\1.corr_fuser.layers.0.\2"),
    (_DECODER_LAYER + r"corr_fuser\.2\.(weight|bias)", r"decoder.layers.\1.corr_fuser.layers.1.\2"),
    (
        r"transformer\.decoder\.corr_query_proj\.0\.(weight|bias)",
        r"decoder.cost_volume.query_proj.layers.0.\1",
    ),
    (
        r"transformer\.decoder\.corr_query_proj\.2\.(weight|bias)",
        r"decoder.cost_volume.query_proj.layers.1.\1",
    ),
    (
        r"transformer\.decoder\.corr_block\.fmap_mappers\.(\d)\.(weight|bias)",
        r"decoder.cost_volume.fmap_mappers.\1.\2",
    ),
    (
        r"transformer\.decoder\.ref_point_head\.layers\.(\d)\.(weight|bias)",
        r"decoder.position_embed.layers.\1.\2",
    ),
    (
        r"transformer\.decoder\.query_updater\.0\.(weight|bias)",
        r"decoder.content_updater.layers.0.\1",
    ),
    (
        r"transformer\.decoder\.query_updater\.2\.(weight|bias)",
        r"decoder.content_updater.layers.1.\1",
    ),
    (
        r"transformer\.decoder\.ca_update_fuser\.0\.(weight|bias)",
        r"decoder.update_fuser.layers.0.\1",
    ),
    (
        r"transformer\.decoder\.ca_update_fuser\.2\.(weight|bias)",
        r"decoder.update_fuser.layers.1.\1",
    ),
    (
        r"transformer\.decoder\.ca_update_fuser\.4\.(weight|bias)",
        r"decoder.update_fuser.layers.2.\1",
    ),
    (r"transformer\.query_feature_initializer\.(weight|bias)", r"query_init.project.\1"),
    (r"bbox_embed\.(\d+)\.layers\.(\d)\.(weight|bias)", r"decoder.position_heads.\1.layers.\2.\3"),
    (r"class_embed\.(\d+)\.(weight|bias)", r"decoder.visibility_heads.\1.\2"),
    (r"query_between_window_updater\.0\.(weight|bias)", r"window_updater.layers.0.\1"),
    (r"query_between_window_updater\.2\.(weight|bias)", r"window_updater.layers.1.\1"),
)
_COMPILED = tuple((re.compile(pattern + r"$"), target) for pattern, target in RULES)

ALIAS_PREFIXES = {
    "transformer.decoder.bbox_embed.": "bbox_embed.",
    "transformer.decoder.class_embed.": "class_embed.",
}


class ConversionError(ValueError):
    """The state dict is not an official TAPTR checkpoint, with every reason listed."""


def official_weights(checkpoint: Mapping[str, object]) -> Mapping[str, Tensor]:
    """Picks the inference weights out of an official training checkpoint.

    The evaluation and demo scripts of the authors load ``ema_model``; a checkpoint
    without EMA falls back to ``model``; a bare state dict is returned as is.
    """
    for key in ("ema_model", "model"):
        weights = checkpoint.get(key)
        if isinstance(weights, Mapping):
            return weights  # type: ignore[return-value]
    return checkpoint  # type: ignore[return-value]


def strip_prefix(state_dict: Mapping[str, Tensor], prefix: str = "module.") -> dict[str, Tensor]:
    """Removes a DistributedDataParallel prefix from every key that has it."""
    return {k[len(prefix) :] if k.startswith(prefix) else k: v for k, v in state_dict.items()}


def _rename(key: str) -> str | None:
    matches = [pattern.sub(target, key) for pattern, target in _COMPILED if pattern.match(key)]
    return matches[0] if len(matches) == 1 else None


def convert_state_dict(state_dict: Mapping[str, Tensor]) -> tuple[dict[str, Tensor], list[str]]:
    """Maps official key names onto taptr's.

    Args:
        state_dict: official weights, with or without the ``module.`` prefix.

    Returns:
        The converted state dict and the list of dropped alias keys.

    Raises:
        ConversionError: listing keys that match no rule and aliases that differ from
            the tensors they should duplicate.
    """
    weights = strip_prefix(state_dict)
    converted: dict[str, Tensor] = {}
    dropped, unknown, bad_alias = [], [], []
    for key, value in weights.items():
        alias_of = next(
            (canon + key[len(a) :] for a, canon in ALIAS_PREFIXES.items() if key.startswith(a)),
            None,
        )
        if alias_of is not None:
            original = weights.get(alias_of)
            if (
                original is None
                or original.shape != value.shape
                or not bool((original == value).all())
            ):
                bad_alias.append(f"{key} (should equal {alias_of})")
            dropped.append(key)
            continue
        new_key = _rename(key)
        if new_key is None:
            unknown.append(key)
        else:
            converted[new_key] = value
    problems = []
    if unknown:
        problems.append(f"{len(unknown)} keys of no known TAPTR module: {_preview(unknown)}")
    if bad_alias:
        problems.append(
            f"{len(bad_alias)} aliased head keys differ from their originals: {_preview(bad_alias)}"
        )
    if problems:
        raise ConversionError("not an official TAPTR checkpoint: " + "; ".join(problems))
    return converted, dropped


def _preview(keys: list[str], limit: int = 8) -> str:
    shown = ", ".join(keys[:limit])
    return shown + (f", ... ({len(keys) - limit} more)" if len(keys) > limit else "")


def official_version(converted: Mapping[str, Tensor]) -> int:
    """The TAPTR generation of a converted official state dict, from its key names.

    1 for TAPTR (it has the cost volume), 3 for TAPTRv3 (the long-temporal attention),
    else 2 (TAPTRv2).
    """
    if any(key.startswith("decoder.cost_volume.") for key in converted):
        return 1
    if any(".long_temporal." in key for key in converted):
        return 3
    return 2


RESNET50_ONLY_KEY = "backbone.body.layer1.0.conv3.weight"
"""A bottleneck's third convolution: in ResNet-50, not in ResNet-18."""


def official_config(converted: Mapping[str, Tensor]) -> ModelConfig:
    """The released model a converted official state dict belongs to, from its key names.

    TAPTR v1, TAPTRv2, or TAPTRv3 with ResNet-50 (512 × 512) or ResNet-18 (384 × 512),
    told apart by the backbone's keys.
    """
    version = official_version(converted)
    if version == 1:
        return taptrv1()
    if version == 2:
        return taptrv2()
    return taptrv3_r50() if RESNET50_ONLY_KEY in converted else taptrv3()


def looks_official(checkpoint: Mapping[str, object]) -> bool:
    """Whether a loaded file has the official layout (EMA/model dicts or official key names)."""
    weights = official_weights(checkpoint)
    return any(
        str(k).replace("module.", "", 1).startswith(("transformer.", "backbone.0.body."))
        for k in weights
    )
