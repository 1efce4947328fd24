"""TAPTRv3: what differs from TAPTRv2, on top of the shared modules.

- `taptr.model.v3.long_temporal`: the visibility-aware long-temporal attention over each
  point's past frames, with the rotary time embedding (`taptr.model.v3.rotary`);
- `taptr.model.v3.context_attention`: the context-aware cross-attention (key patches
  against the point's initial context), whose logits drive TAPTRv2's position update;
- `taptr.model.v3.context`: each point's content and K × K context on its start frame;
- `taptr.model.v3.decoder`: the layer order (long-temporal, cross, point attention, FFN)
  on one frame;
- `taptr.model.v3.taptr`: the module; `taptr.model.v3.per_frame`: its frame-by-frame
  driver over the per-point history (`taptr.model.v3.history`).

`taptr.model.build.build_model` picks these for configs with ``version == 3``.
"""

from taptr.model.v3.context import ContextInitializer
from taptr.model.v3.context_attention import ContextAwareDeformableAttention
from taptr.model.v3.decoder import HeldFrames, V3Decoder, V3DecoderLayer
from taptr.model.v3.long_temporal import LongTemporalAttention
from taptr.model.v3.taptr import TAPTRv3

__all__ = [
    "ContextAwareDeformableAttention",
    "ContextInitializer",
    "HeldFrames",
    "LongTemporalAttention",
    "TAPTRv3",
    "V3Decoder",
    "V3DecoderLayer",
]
