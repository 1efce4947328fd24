"""Exponential moving average of the model weights, the weights inference uses.

After each update, ``ema ← d·ema + (1 − d)·weights`` for every floating state-dict entry
(parameters and buffers, as the official ``ModelEma``); integer buffers are copied. The
official code updates after every micro-batch, while the weights only change at optimizer
steps; k identical updates equal one update with decay d^k, so `update(model, steps=k)`
reproduces it once per optimizer step.
"""

from __future__ import annotations

import copy
from typing import Generic, TypeVar

import torch
from torch import Tensor, nn

ModuleT = TypeVar("ModuleT", bound=nn.Module)


class ModelEMA(Generic[ModuleT]):
    """A frozen copy of a model that follows its weights.

    Attributes:
        module: the averaged model (eval mode, no gradients).
        decay: decay per update step.
    """

    def __init__(self, model: ModuleT, decay: float) -> None:
        self.module: ModuleT = copy.deepcopy(model).eval()
        self.module.requires_grad_(False)
        self.decay = decay

    @torch.no_grad()
    def update(self, model: nn.Module, steps: int = 1) -> None:
        """Moves the average towards ``model``'s weights, as ``steps`` single updates would."""
        decay = self.decay**steps
        current = model.state_dict()
        for name, averaged in self.module.state_dict().items():
            value = current[name].detach()
            if averaged.is_floating_point():
                averaged.mul_(decay).add_(value.to(averaged.dtype), alpha=1 - decay)
            else:
                averaged.copy_(value)

    def state_dict(self) -> dict[str, Tensor]:
        """The averaged weights."""
        return self.module.state_dict()

    def load_state_dict(self, state_dict: dict[str, Tensor]) -> None:
        """Restores averaged weights (strict)."""
        self.module.load_state_dict(state_dict, strict=True)
