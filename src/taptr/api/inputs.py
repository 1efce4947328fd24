"""Validation and normalisation of what users pass to the predictor.

Every check raises a one-line ValueError that names the problem (shape, dtype, range,
NaN), so that the CLI can print it without a traceback.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor


def video_tensor(video: np.ndarray | Tensor) -> Tensor:
    """Brings a video to (B, T, 3, H, W), uint8 or float in [0, 1], without copying it.

    Frames stay in their input type (a float copy of a long video would take four times
    its memory); `as_unit_float` converts them window by window.

    Args:
        video: a uint8 numpy array (T, H, W, 3), or a torch tensor (B, T, 3, H, W) of
            uint8 or of floats in [0, 1].
    """
    if isinstance(video, np.ndarray):
        if video.ndim != 4 or video.shape[-1] != 3:
            raise ValueError(f"a numpy video must be (T, H, W, 3), got shape {video.shape}")
        if video.dtype != np.uint8:
            raise ValueError(f"a numpy video must be uint8, got {video.dtype}")
        return torch.from_numpy(video).permute(0, 3, 1, 2)[None]  # a view: (1, T, 3, H, W)
    if not isinstance(video, Tensor):
        raise ValueError(
            f"video must be a numpy array, a torch tensor or a path, got {type(video).__name__}"
        )
    if video.dim() != 5 or video.shape[2] != 3:
        raise ValueError(f"a tensor video must be (B, T, 3, H, W), got shape {tuple(video.shape)}")
    if video.dtype == torch.uint8:
        return video
    if not video.is_floating_point():
        raise ValueError(f"a tensor video must be uint8 or float, got {video.dtype}")
    if video.numel() and not bool(torch.isfinite(video).all()):
        raise ValueError("the video contains NaN or infinite values")
    if video.numel() and (float(video.max()) > 1 or float(video.min()) < 0):
        raise ValueError("a float video must lie in [0, 1]; pass uint8 frames or divide by 255")
    return video


def as_unit_float(frames: Tensor) -> Tensor:
    """uint8 frames → float32 in [0, 1]; float frames are returned as float32."""
    return frames.float() / 255 if frames.dtype == torch.uint8 else frames.float()


def query_tensor(
    queries: np.ndarray | Tensor, batch: int, num_frames: int, height: int, width: int
) -> Tensor:
    """Validates (t, x, y) pixel queries and returns them as (B, N, 3) float32.

    Args:
        queries: (N, 3) or (B, N, 3) as (t, x, y): frame index and pixel position with
            pixel centres at integers.
        batch: number of videos B.
        num_frames: frames T of the video.
        height: frame height H in pixels.
        width: frame width W in pixels.
    """
    q = torch.as_tensor(np.asarray(queries) if not isinstance(queries, Tensor) else queries)
    q = q.detach().to("cpu", torch.float64)
    if q.dim() == 2:
        q = q[None].expand(batch, -1, -1)
    if q.dim() != 3 or q.shape[-1] != 3 or q.shape[0] != batch:
        raise ValueError(
            f"queries must be (N, 3) or (B={batch}, N, 3) as (t, x, y), got {tuple(q.shape)}"
        )
    if not bool(torch.isfinite(q).all()):
        raise ValueError("queries contain NaN or infinite values")
    t, x, y = q.unbind(-1)
    if bool((t != t.round()).any()):
        raise ValueError("query frames t must be whole frame indices")
    if q.shape[1] and (float(t.min()) < 0 or float(t.max()) >= num_frames):
        raise ValueError(
            f"query frame t outside [0, {num_frames}) (got {int(t.min())}..{int(t.max())})"
        )
    # pixel centres sit at integers, so the image area spans [-0.5, size - 0.5]
    bad_x = bool(((x < -0.5) | (x > width - 0.5)).any())
    bad_y = bool(((y < -0.5) | (y > height - 0.5)).any())
    if bad_x or bad_y:
        raise ValueError(
            f"query positions outside the {width}x{height} frame: x must lie in "
            f"[-0.5, {width - 0.5}] and y in [-0.5, {height - 0.5}] (pixel centres at integers)"
        )
    return q.float()


def grid_queries(grid_size: int, frame: int, height: int, width: int) -> Tensor:
    """A grid_size × grid_size grid of queries at cell centres of one frame, (N, 3) as (t, x, y)."""
    if grid_size < 1:
        raise ValueError(f"grid_size must be at least 1, got {grid_size}")
    xs = (torch.arange(grid_size, dtype=torch.float32) + 0.5) * width / grid_size - 0.5
    ys = (torch.arange(grid_size, dtype=torch.float32) + 0.5) * height / grid_size - 0.5
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack((torch.full_like(gx, float(frame)), gx, gy), dim=-1).view(-1, 3)
