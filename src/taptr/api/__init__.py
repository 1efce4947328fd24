"""The user-facing API: the predictor, its input handling, and the model type it wraps.

`TAPTR` (the network's type) and `normalize_frames` (its ImageNet input normalisation) are
named here so that code outside the model package (the evaluation) needs no model internals.
Names are imported on first use, as `taptr`'s own are: the torch-free modules of this
package (the region queries, `taptr.api.regions`) load without torch.
"""

from __future__ import annotations

from taptr.lazy import lazy_names

_EXPORTS = {
    "Predictor": "taptr.api.predictor",
    "TAPTR": "taptr.model.taptr",
    "normalize_frames": "taptr.model.taptr",
}

__all__ = sorted(_EXPORTS)


__getattr__ = lazy_names(__name__, _EXPORTS)
