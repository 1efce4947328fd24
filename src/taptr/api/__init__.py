"""The user-facing API: the predictor and its input handling."""

from taptr.api.predictor import Predictor

__all__ = ["Predictor"]
