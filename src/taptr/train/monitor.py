"""Progress reporting of rank 0: console lines through `logging`, and TensorBoard scalars.

TensorBoard is optional (the ``train`` extra); without it the run logs to the
console only, after one warning.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

from taptr.messages import install_line

logger = logging.getLogger(__name__)


def summary_writer(log_dir: Path) -> Any | None:
    """A TensorBoard writer, or None (with a warning) when tensorboard is not installed."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        logger.warning(
            "tensorboard is not installed (%s): logging to the console only", install_line("train")
        )
        return None
    return SummaryWriter(str(log_dir))


def _duration(seconds: float) -> str:
    minutes, seconds = divmod(int(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}h{minutes:02d}m" if hours else f"{minutes}m{seconds:02d}s"


class Monitor:
    """Logs training scalars and timing; silent on ranks other than 0.

    Args:
        log_dir: where TensorBoard events go.
        enabled: whether this process reports (rank 0).
        total_steps: the run's optimizer steps (for the time estimate).
        first_step: steps already done (when resuming).
    """

    def __init__(self, log_dir: Path, enabled: bool, total_steps: int, first_step: int = 0):
        self.enabled = enabled
        self.total_steps = total_steps
        self.writer = summary_writer(log_dir) if enabled else None
        self.last_step, self.last_time = first_step, time.perf_counter()
        self.sums: dict[str, float] = defaultdict(float)
        self.count = 0

    def add(self, scalars: dict[str, float]) -> None:
        """Accumulates one step's scalars (on every process, for the cross-process mean)."""
        for name, value in scalars.items():
            self.sums[name] += value
        self.count += 1

    def means(self) -> dict[str, float]:
        """Averages of the scalars added since the last call."""
        means = {name: total / max(self.count, 1) for name, total in self.sums.items()}
        self.sums.clear()
        self.count = 0
        return means

    def seconds_per_step(self, step: int) -> float:
        """Average wall time per step since the previous call; resets the clock."""
        now = time.perf_counter()
        elapsed = (now - self.last_time) / max(step - self.last_step, 1)
        self.last_step, self.last_time = step, now
        return elapsed

    def train(self, step: int, scalars: dict[str, float]) -> None:
        """Reports training scalars after ``step`` steps (``loss`` and ``lr`` are shown).

        ``scalars`` are means over the steps since the previous report (see `means`).
        """
        seconds = self.seconds_per_step(step)
        if not self.enabled:
            return
        remaining = _duration(seconds * (self.total_steps - step))
        position = scalars.get(f"position_{self._last_layer(scalars)}", float("nan"))
        logger.info(
            "step %d/%d  loss %.4f  position %.4f  lr %.2e  grad %.3f  %.2f s/step  eta %s",
            step,
            self.total_steps,
            scalars["loss"],
            position,
            scalars["lr"],
            scalars.get("grad_norm", float("nan")),
            seconds,
            remaining,
        )
        self._write("train", step, {**scalars, "seconds_per_step": seconds})

    def evaluation(self, step: int, metrics: dict[str, float]) -> None:
        """Reports held-out metrics after ``step`` steps."""
        if not self.enabled:
            return
        logger.info(
            "eval step %d  loss %.4f  position error %.2f px  AJ %.3f  delta_avg %.3f  OA %.3f",
            step,
            metrics["loss"],
            metrics["position_error"],
            metrics["average_jaccard"],
            metrics["average_pts_within_thresh"],
            metrics["occlusion_accuracy"],
        )
        self._write("val", step, metrics)

    @staticmethod
    def _last_layer(scalars: dict[str, float]) -> int:
        layers = [int(k.rsplit("_", 1)[1]) for k in scalars if k.startswith("position_")]
        return max(layers, default=0)

    def _write(self, group: str, step: int, scalars: dict[str, float]) -> None:
        if self.writer is None:
            return
        for name, value in scalars.items():
            self.writer.add_scalar(f"{group}/{name}", value, step)
        self.writer.flush()

    def close(self) -> None:
        """Closes the TensorBoard writer."""
        if self.writer is not None:
            self.writer.close()
