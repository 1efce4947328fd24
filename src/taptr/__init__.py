"""taptr: Tracking Any Point with TAPTR v1, TAPTRv2 and TAPTRv3, in pure PyTorch.

Heavy modules (torch, the model) are imported on first use of a name, not at import.
"""

from __future__ import annotations

from taptr.lazy import lazy_names

__version__ = "0.1.0"

_EXPORTS = {
    "build_model": "taptr.model.build",
    "from_pretrained": "taptr.weights.registry",
    "load_checkpoint": "taptr.weights.checkpoint",
    "save_checkpoint": "taptr.weights.checkpoint",
    "official_forward": "taptr.official.model_forward",
    "ModelConfig": "taptr.config",
    "BackboneConfig": "taptr.config",
    "get_config": "taptr.config",
    "PRESETS": "taptr.config",
    "Predictor": "taptr.api.predictor",
    "TrackingResult": "taptr.types",
    "TrackingSample": "taptr.types",
}

__all__ = ["__version__", *sorted(_EXPORTS)]


__getattr__ = lazy_names(__name__, _EXPORTS)
