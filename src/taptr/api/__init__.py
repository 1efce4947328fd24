"""The user-facing API: the predictor, its input handling, and the model type it wraps.

`TAPTR` (the network's type) and `normalize_frames` (its ImageNet input normalisation) are
named here so that code outside the model package (the evaluation) needs no model internals.
"""

from taptr.api.predictor import Predictor
from taptr.model.taptr import TAPTR, normalize_frames

__all__ = ["TAPTR", "Predictor", "normalize_frames"]
