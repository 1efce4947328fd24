"""`build_model`: the only place that reads a `ModelConfig`.

Fresh weights follow the official initialisation (spec §5.4): xavier-uniform on every
matrix of the transformer, Deformable DETR's reset of the encoder attention, a radial
offset bias in the decoder cross-attention, level embeddings ~ N(0, 1), visibility biases
−log(99), zero last layers in the position heads, and PyTorch defaults for the modules the
official code adds after the transformer (query initialiser, content updaters).
"""

from __future__ import annotations

import math

from torch import nn

from taptr.config import ModelConfig, get_config
from taptr.model.attention import (
    DeformableAttention,
    KeyAwareDeformableAttention,
    MultiheadAttention,
)
from taptr.model.backbone import Backbone, ConvNet, InputProjections, ResNetBody
from taptr.model.decoder import Decoder, DecoderLayer
from taptr.model.encoder import Encoder, EncoderLayer
from taptr.model.execution import DEFAULT_EXECUTION, Execution, get_execution
from taptr.model.layers import MLP
from taptr.model.position_update import PositionUpdate, refine_updated
from taptr.model.query_init import QueryInitializer
from taptr.model.taptr import TAPTR
from taptr.model.v1 import CostVolume, V1Decoder, V1DecoderLayer, look_forward_twice
from taptr.model.v3 import (
    ContextAwareDeformableAttention,
    ContextInitializer,
    LongTemporalAttention,
    TAPTRv3,
    V3Decoder,
    V3DecoderLayer,
)

COST_VOLUME_RADIUS = 3
"""TAPTR v1 samples 7×7 correlation windows."""


def _build_backbone(config: ModelConfig) -> Backbone:
    if config.backbone.kind in ("resnet50", "resnet18"):
        return Backbone(ResNetBody(config.backbone.kind))
    return Backbone(ConvNet(config.backbone.channels))


def _build_encoder(config: ModelConfig) -> Encoder:
    layers = [
        EncoderLayer(
            DeformableAttention(
                config.d_model, config.num_heads, config.num_levels, config.encoder_points
            ),
            config.d_model,
            config.ffn_dim,
        )
        for _ in range(config.encoder_layers)
    ]
    return Encoder(layers, config.d_model, config.sine_temperature, config.num_levels)


def _build_decoder_layer(config: ModelConfig) -> DecoderLayer:
    c, m, lv, p = config.d_model, config.num_heads, config.num_levels, config.decoder_points
    cross: KeyAwareDeformableAttention | DeformableAttention
    if config.cross_attention == "key_aware":
        cross = KeyAwareDeformableAttention(c, m, lv, p)
    else:
        cross = DeformableAttention(c, m, lv, p)
    update = PositionUpdate(m * lv * p, c, config.disentangler) if config.position_update else None
    temporal = MultiheadAttention(c, m) if config.temporal_attention else None
    points = MultiheadAttention(c, m) if config.point_attention else None
    if config.version == 1:
        # v1 has no position update and plain cross-attention (checked by the config)
        assert update is None and isinstance(cross, DeformableAttention)
        corr_values = lv * (2 * COST_VOLUME_RADIUS + 1) ** 2
        fuser = MLP(c + corr_values, c, c, 2) if config.cost_volume else None
        return V1DecoderLayer(
            cross, temporal, points, c, config.ffn_dim, config.sine_temperature, fuser
        )
    return DecoderLayer(cross, update, temporal, points, c, config.ffn_dim, config.sine_temperature)


def _build_v3_layer(config: ModelConfig) -> V3DecoderLayer:
    c, m, lv, p = config.d_model, config.num_heads, config.num_levels, config.decoder_points
    cross: ContextAwareDeformableAttention | KeyAwareDeformableAttention
    if config.context_attention:
        cross = ContextAwareDeformableAttention(c, m, lv, p, config.context_patch)
    else:
        cross = KeyAwareDeformableAttention(c, m, lv, p)
    return V3DecoderLayer(
        cross,
        PositionUpdate(m * lv * p, c, config.disentangler),
        MultiheadAttention(c, m) if config.point_attention else None,
        LongTemporalAttention(c, m),
        c,
        config.ffn_dim,
        config.sine_temperature,
    )


def _build_decoder(config: ModelConfig) -> Decoder:
    c = config.d_model
    if config.version == 3:
        layers_v3 = [_build_v3_layer(config) for _ in range(config.decoder_layers)]
        return V3Decoder(layers_v3, c, config.sine_temperature, MLP(2 * c, c, c, 3))
    fuser = MLP(2 * c, c, c, 3) if config.position_update else None
    layers = [_build_decoder_layer(config) for _ in range(config.decoder_layers)]
    if config.version == 1:
        cost_volume = (
            CostVolume(c, config.num_levels, COST_VOLUME_RADIUS) if config.cost_volume else None
        )
        v1_layers = [layer for layer in layers if isinstance(layer, V1DecoderLayer)]
        return V1Decoder(v1_layers, c, config.sine_temperature, cost_volume)
    # without the APU (an ablation) the reported positions follow v1's rule
    refine = refine_updated if config.position_update else look_forward_twice
    return Decoder(layers, c, config.sine_temperature, fuser, refine)


def _init_transformer(encoder: Encoder, decoder: Decoder) -> None:
    # modules the official code creates after the transformer's reset keep PyTorch defaults
    late_modules: list[nn.Module] = [
        decoder.content_updater,
        decoder.position_heads,
        decoder.visibility_heads,
    ]
    if isinstance(decoder, V1Decoder) and decoder.cost_volume is not None:
        late_modules.append(decoder.cost_volume)
    late_modules += [
        layer.corr_fuser
        for layer in decoder.layers
        if isinstance(layer, V1DecoderLayer) and layer.corr_fuser is not None
    ]
    late = {id(p) for module in late_modules for p in module.parameters()}
    params = [*encoder.parameters(), *decoder.parameters()]
    for param in params:
        if param.dim() > 1 and id(param) not in late:
            nn.init.xavier_uniform_(param)
    for module in [*encoder.modules(), *decoder.modules()]:
        if isinstance(module, DeformableAttention):
            module.reset_parameters()
    nn.init.normal_(encoder.level_embed)
    prior = -math.log((1 - 0.01) / 0.01)
    for head in decoder.visibility_heads.modules():
        if isinstance(head, nn.Linear):
            nn.init.constant_(head.bias, prior)
    for mlp in decoder.position_heads.modules():
        if isinstance(mlp, MLP):
            last = mlp.layers[-1]
            assert isinstance(last, nn.Linear)
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)


def build_model(config: str | ModelConfig, execution: str | Execution = DEFAULT_EXECUTION) -> TAPTR:
    """Builds a freshly initialised model from a preset name or a config.

    Args:
        config: a preset name (``"taptrv2"``, ``"tiny"``) or a `ModelConfig`.
        execution: how the model runs, a name of `taptr.model.execution.EXECUTIONS`
            (``"fast"``, the default for inference; ``"reference"``; ``"training"``) or an
            `Execution`; change it later with `TAPTR.set_execution`.

    Returns:
        The model in training mode, with ``model.config`` and ``model.execution`` set.

    Raises:
        ValueError: for an unknown execution name.
    """
    chosen = get_execution(execution)
    if isinstance(config, str):
        config = get_config(config)
    backbone = _build_backbone(config)
    encoder = _build_encoder(config)
    decoder = _build_decoder(config)
    _init_transformer(encoder, decoder)
    if isinstance(decoder, V3Decoder):
        return _assemble_v3(config, backbone, encoder, decoder, chosen)
    return TAPTR(
        backbone,
        InputProjections(backbone.channels, config.d_model),
        encoder,
        QueryInitializer(config.d_model, config.num_levels),
        decoder,
        MLP(3 * config.d_model, config.d_model, config.d_model, 2),
        window_size=config.window_size,
        window_stride=config.window_stride,
        long_video_frames=config.long_video_frames,
        window_dropout=config.window_dropout,
        memory_efficient=config.memory_efficient,
        config=config,
        execution=chosen,
    )


def _assemble_v3(
    config: ModelConfig,
    backbone: Backbone,
    encoder: Encoder,
    decoder: V3Decoder,
    execution: Execution,
) -> TAPTRv3:
    query_init = (
        ContextInitializer(config.d_model, config.num_levels, config.context_patch)
        if config.context_attention
        else QueryInitializer(config.d_model, config.num_levels)
    )
    return TAPTRv3(
        backbone,
        InputProjections(backbone.channels, config.d_model),
        encoder,
        query_init,
        decoder,
        visibility_weights=config.visibility_weights,
        history_frames=config.history_frames,
        config=config,
        execution=execution,
    )
