"""Per-frame trajectories with a shared value for every frame not yet reached.

The window driver writes results window by window and copies a window's last frame to all
later frames. Keeping those later frames as one shared tensor makes the copy free, keeps
memory bounded by the frames still in use, and lets finished frames be released.
"""

from __future__ import annotations

import torch
from torch import Tensor


class Trajectory:
    """Per-frame values of one quantity, from frame ``first`` on, plus the shared future.

    Frames ``first .. first + len(frames) - 1`` are held as separate (B, N, D) tensors;
    every later frame holds ``future``. Writes build new tensors, so autograd sees every
    window's contribution.
    """

    def __init__(self, future: Tensor) -> None:
        self.first = 0
        self.frames: list[Tensor] = []
        self.future = future

    @property
    def end(self) -> int:
        """One past the last held frame."""
        return self.first + len(self.frames)

    def _extend(self, last: int) -> None:
        self.frames.extend([self.future] * (last + 1 - self.end))

    def read(self, first: int, last: int) -> Tensor:
        """Values of frames first..last, (B, W_t, N, D)."""
        if first < self.first:
            raise IndexError(f"frame {first} was already released (first held: {self.first})")
        self._extend(last)
        return torch.stack(self.frames[first - self.first : last + 1 - self.first], dim=1)

    def write(self, first: int, values: Tensor, mask: Tensor) -> None:
        """Overwrites frames first.. where ``mask`` holds.

        Args:
            first: first frame written.
            values: (B, W_t, N, D) new values.
            mask: (B, W_t, N) bool, where to write.
        """
        self._extend(first + values.shape[1] - 1)
        for offset in range(values.shape[1]):
            index = first + offset - self.first
            self.frames[index] = torch.where(
                mask[:, offset, :, None], values[:, offset], self.frames[index]
            )

    def fill(self, select: Tensor, value: Tensor) -> None:
        """Sets every held and future frame of the selected points, (B, N) and (B, N, D)."""
        self.frames = [torch.where(select[..., None], value, f) for f in self.frames]
        self.future = torch.where(select[..., None], value, self.future)

    def pad_from(self, frame: int) -> None:
        """Every frame after ``frame`` takes its value (the official padding)."""
        self.future = self.frames[frame - self.first]
        del self.frames[frame + 1 - self.first :]

    def add_points(self, values: Tensor) -> None:
        """Appends points holding ``values`` (B, n, D) on every held and future frame."""
        self.frames = [torch.cat((f, values), dim=1) for f in self.frames]
        self.future = torch.cat((self.future, values), dim=1)

    def keep_points(self, keep: Tensor) -> None:
        """Keeps only the points selected by the (N,) bool mask."""
        self.frames = [f[:, keep] for f in self.frames]
        self.future = self.future[:, keep]

    def release(self, before: int) -> list[Tensor]:
        """Drops and returns the held frames before ``before``."""
        count = max(0, min(before - self.first, len(self.frames)))
        released, self.frames = self.frames[:count], self.frames[count:]
        self.first += count
        return released
