"""TAPTR (v1): what differs from TAPTRv2, on top of the shared v2 modules.

- `taptr.model.v1.decoder`: v1's layer order (cost-volume fusion, temporal attention,
  point attention, plain cross-attention, FFN), the content updater from the first layer,
  and the "look forward twice" rule of its reported positions;
- `taptr.model.v1.cost_volume`: the correlation of each point with its frame;
- `taptr.model.v1.memory_efficient`: the memory-efficient initialisation of the tracker.

`taptr.model.build.build_model` picks these for configs with ``version == 1``; parameter
names are those of the official v1 checkpoint as converted by `taptr.official.convert`.
"""

from taptr.model.v1.cost_volume import CostVolume
from taptr.model.v1.decoder import V1Decoder, V1DecoderLayer, look_forward_twice

__all__ = ["CostVolume", "V1Decoder", "V1DecoderLayer", "look_forward_twice"]
