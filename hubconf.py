"""torch.hub entry points: ``torch.hub.load("<owner>/taptr", "taptrv2")``.

Each entry point returns a ready `taptr.Predictor` (pixels and (t, x, y) queries in, tracks
and visibility out); its ``.model`` is the ``nn.Module``. Weights resolve as in
``taptr.from_pretrained``: the authors' releases come through the Hugging Face cache
(downloaded once unless ``HF_HUB_OFFLINE=1``), the bundled model from the package.
Keyword arguments go to the `Predictor` (``device``, ``dtype``, ``input_size``,
``visibility_threshold``).
"""

from __future__ import annotations

import sys as _sys
from pathlib import Path as _Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from typing import Any

    from taptr.api.predictor import Predictor

dependencies = ["torch", "torchvision", "numpy", "tqdm"]

# a checkout fetched by torch.hub is not installed: import the package from its src folder
_SOURCE = _Path(__file__).resolve().parent / "src"
if _SOURCE.is_dir() and str(_SOURCE) not in _sys.path:
    _sys.path.insert(0, str(_SOURCE))

# torch.hub lists every public callable here as an entry point: keep helpers private
from taptr.api.predictor import Predictor as _Predictor  # noqa: E402
from taptr.config import PRESETS as _PRESETS  # noqa: E402


def taptrv2(pretrained: bool = True, **kwargs: Any) -> Predictor:
    """TAPTRv2, the paper's model (ResNet-50, 512 × 512 input).

    Args:
        pretrained: the authors' released weights (``taptrv2-official``); False gives
            untrained weights.
        **kwargs: `Predictor` options.
    """
    return _Predictor.from_pretrained("taptrv2-official" if pretrained else "taptrv2", **kwargs)


def taptr_small_synthetic(**kwargs: Any) -> Predictor:
    """The small model bundled with the package, trained on synthetic data only.

    Args:
        **kwargs: `Predictor` options.
    """
    return _Predictor.from_pretrained("taptr-small-synthetic", **kwargs)


if "taptrv1" in _PRESETS:

    def taptrv1(pretrained: bool = True, **kwargs: Any) -> Predictor:
        """TAPTR (v1) as the authors released it.

        Args:
            pretrained: the authors' released weights (``taptrv1-official``); False gives
                untrained weights.
            **kwargs: `Predictor` options.
        """
        return _Predictor.from_pretrained("taptrv1-official" if pretrained else "taptrv1", **kwargs)
