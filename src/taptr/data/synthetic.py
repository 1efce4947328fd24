"""Procedural training and test videos with exact ground-truth tracks and occlusion.

A video is a stack of layers drawn back to front: a textured background seen through a
moving camera (pan, slow rotation and zoom), then several textured objects of random shape,
each with its own affine motion (translation, rotation, scaling) and a fixed depth order.
Every layer is warped with one 2×3 affine per frame (OpenCV, pixel centres at integers), so
a point on a layer moves by exactly that affine. Each frame also records which layer owns
every pixel (its mask covers at least half of it), which gives real occlusions: a point is
visible where its own layer owns its pixel and it lies inside the image. Points that leave
the image are marked not visible and keep their (outside) coordinates.

Points are sampled like Kubric's: at a random pixel of a random frame (often the first or
the middle one), on whatever layer is visible there, then followed through the whole video.
Everything is drawn from one numpy generator, so a seed gives the same video everywhere.
`write_dataset` stores videos in the Kubric layout (`taptr.data.kubric`), so the same
reader loads them.

Given photographs (``photos``, see `taptr.data.photos`), each layer is a random crop of one
with probability ``photo_prob`` instead of procedural noise. Only the layers' colours change:
the warps, masks, occlusions and tracks are drawn exactly as without photographs. Without
photographs no extra random number is drawn, so earlier seeds give the same videos.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from taptr.data.kubric import write_sequence
from taptr.data.photos import photo_texture
from taptr.types import TrackingSample


@dataclass(frozen=True)
class SyntheticConfig:
    """Size and motion of the generated videos.

    Attributes:
        height: frame height H in pixels.
        width: frame width W in pixels.
        num_frames: frames T per video.
        num_points: tracks N per video.
        objects: (min, max) number of moving objects.
        camera_speed: largest camera pan per frame, in pixels.
        object_speed: largest object translation per frame, in pixels.
    """

    height: int = 256
    width: int = 256
    num_frames: int = 24
    num_points: int = 1024
    objects: tuple[int, int] = (3, 6)
    camera_speed: float = 3.0
    object_speed: float = 4.0

    def __post_init__(self) -> None:
        if min(self.height, self.width) < 16 or self.num_frames < 1 or self.num_points < 1:
            raise ValueError("need frames of at least 16×16 pixels, one frame and one point")
        if not 0 <= self.objects[0] <= self.objects[1]:
            raise ValueError(f"objects must be (min, max) with 0 <= min <= max, got {self.objects}")


def _affine(
    center_to: np.ndarray, angle: float, scale: float, center_from: np.ndarray
) -> np.ndarray:
    """2×3 matrix mapping ``center_from`` to ``center_to``, rotating and scaling about it."""
    cos, sin = scale * np.cos(angle), scale * np.sin(angle)
    linear = np.array([[cos, -sin], [sin, cos]])
    return np.concatenate([linear, (center_to - linear @ center_from)[:, None]], axis=1)


def _texture(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """Coloured multi-scale noise with random strokes, (H, W, 3) uint8."""
    image = np.zeros((height, width, 3), np.float32)
    for cells, weight in ((3, 1.0), (12, 0.8), (max(width, height) // 5, 0.6)):
        noise = rng.random((cells, cells, 3), dtype=np.float32)
        image += weight * cv2.resize(noise, (width, height), interpolation=cv2.INTER_CUBIC)
    # a per-channel contrast stretch undoes the greying of summed noise
    low, high = np.percentile(image.reshape(-1, 3), [2, 98], axis=0)
    image = (255 * (image - low) / np.maximum(high - low, 1e-6)).clip(0, 255).astype(np.uint8)
    # strokes add corners and edges: texture that can be tracked without ambiguity
    for _ in range(int(rng.integers(2, 5) + height * width / 2000)):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        a = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        if rng.random() < 0.5:
            b = a + rng.integers(-width // 4, width // 4 + 1, 2)
            cv2.line(image, a, (int(b[0]), int(b[1])), colour, int(rng.integers(1, 4)), cv2.LINE_AA)
        else:
            cv2.circle(image, a, int(rng.integers(2, 8)), colour, -1, cv2.LINE_AA)
    return image


def _shape_mask(rng: np.random.Generator, size: int) -> np.ndarray:
    """A random ellipse, rectangle or polygon filling most of a (size, size) float mask."""
    mask = np.zeros((size, size), np.uint8)
    half = size / 2
    kind = rng.integers(3)
    if kind == 0:
        axes = (int(half * rng.uniform(0.5, 0.95)), int(half * rng.uniform(0.5, 0.95)))
        cv2.ellipse(mask, (int(half), int(half)), axes, 0, 0, 360, 255, -1, cv2.LINE_AA)
    elif kind == 1:
        low, high = int(size * rng.uniform(0.05, 0.25)), int(size * rng.uniform(0.75, 0.95))
        cv2.rectangle(mask, (low, low), (high, high), 255, -1)
    else:
        angles = np.sort(rng.uniform(0, 2 * np.pi, int(rng.integers(5, 9))))
        radii = half * rng.uniform(0.5, 0.95, angles.size)
        corners = np.stack([half + radii * np.cos(angles), half + radii * np.sin(angles)], -1)
        cv2.fillPoly(mask, [corners.round().astype(np.int32)], 255, cv2.LINE_AA)
    return mask.astype(np.float32) / 255


def _camera_path(rng: np.random.Generator, config: SyntheticConfig, canvas: int) -> np.ndarray:
    """Per-frame 2×3 maps from background-canvas pixels to frame pixels, (T, 2, 3)."""
    frames = np.arange(config.num_frames)
    velocity = rng.uniform(-1, 1, 2) * config.camera_speed
    acceleration = rng.uniform(-1, 1, 2) * config.camera_speed / max(config.num_frames, 1)
    spin, zoom = rng.uniform(-0.004, 0.004), rng.uniform(-0.004, 0.004)
    frame_center = np.array([config.width - 1, config.height - 1]) / 2
    canvas_center = np.full(2, (canvas - 1) / 2)
    return np.stack(
        [
            _affine(
                frame_center,
                spin * t,
                1 + zoom * t,
                canvas_center + velocity * t + 0.5 * acceleration * t * t,
            )
            for t in frames
        ]
    )


def _object_path(rng: np.random.Generator, config: SyntheticConfig, size: int) -> np.ndarray:
    """Per-frame 2×3 maps from object-patch pixels to frame pixels, (T, 2, 3)."""
    start = rng.uniform([0, 0], [config.width - 1, config.height - 1])
    velocity = rng.uniform(-1, 1, 2) * config.object_speed
    angle, spin = rng.uniform(0, 2 * np.pi), rng.uniform(-0.05, 0.05)
    scale, growth = rng.uniform(0.8, 1.2), rng.uniform(-0.01, 0.01)
    patch_center = np.full(2, (size - 1) / 2)
    return np.stack(
        [
            _affine(start + velocity * t, angle + spin * t, scale * (1 + growth * t), patch_center)
            for t in range(config.num_frames)
        ]
    )


def _sample_points(
    rng: np.random.Generator, owner: np.ndarray, paths: np.ndarray, num_points: int
) -> tuple[np.ndarray, np.ndarray]:
    """Random pixels of random frames, lifted to the layer that owns them.

    Returns:
        layer index of each point (N,) and its position in that layer's own pixels (N, 2).
    """
    num_frames, height, width = owner.shape
    frames = rng.choice(
        [0, num_frames // 2, -1], size=num_points, p=[0.35, 0.35, 0.3]
    )  # -1: any frame
    frames = np.where(frames < 0, rng.integers(0, num_frames, num_points), frames)
    xy = rng.uniform([0, 0], [width - 1, height - 1], (num_points, 2))
    layers = owner[frames, xy[:, 1].round().astype(int), xy[:, 0].round().astype(int)]
    maps = paths[layers, frames]  # (N, 2, 3) layer → frame
    linear, offset = maps[:, :, :2], maps[:, :, 2]
    local = np.linalg.solve(linear, (xy - offset)[..., None])[..., 0]
    return layers, local


def _layer_texture(
    rng: np.random.Generator,
    size: int,
    photos: Sequence[np.ndarray] | None,
    photo_prob: float,
    crop: tuple[float, float],
) -> np.ndarray:
    """A (size, size, 3) uint8 texture: a photograph crop with probability ``photo_prob``."""
    # no draw at all without photographs: the procedural videos of a seed stay the same
    if photos and rng.random() < photo_prob:
        return photo_texture(rng, photos, size, size, crop=crop)
    return _texture(rng, size, size)


def make_video(
    rng: np.random.Generator,
    config: SyntheticConfig,
    photos: Sequence[np.ndarray] | None = None,
    photo_prob: float = 0.8,
) -> TrackingSample:
    """Renders one video with its tracks.

    Args:
        rng: the only source of randomness.
        config: sizes and speeds.
        photos: optional photographs, each (h, w, 3) uint8 RGB, to texture the layers with.
        photo_prob: probability that a layer is textured with a photograph (when given).

    Returns:
        video (T, H, W, 3) uint8 RGB, tracks (T, N, 2) float32 pixels, visible (T, N).
    """
    if not 0 <= photo_prob <= 1:
        raise ValueError(f"photo_prob must lie in [0, 1], got {photo_prob}")
    height, width, num_frames = config.height, config.width, config.num_frames
    # the canvas covers the frame under the largest pan, rotation and zoom of _camera_path
    reach = (config.camera_speed + config.camera_speed / 2) * num_frames
    canvas = int(1.3 * max(height, width) + 2 * reach)
    # the background crop is kept large: a small crop blown up to the canvas is a blur
    textures = [_layer_texture(rng, canvas, photos, photo_prob, (0.6, 1.0))]
    masks = [np.ones((canvas, canvas), np.float32)]
    paths = [_camera_path(rng, config, canvas)]
    for _ in range(int(rng.integers(config.objects[0], config.objects[1] + 1))):
        size = int(min(height, width) * rng.uniform(0.2, 0.5))
        textures.append(_layer_texture(rng, size, photos, photo_prob, (0.3, 1.0)))
        masks.append(_shape_mask(rng, size))
        paths.append(_object_path(rng, config, size))
    maps = np.stack(paths)  # (layers, T, 2, 3), layer order = depth order, back to front

    video = np.zeros((num_frames, height, width, 3), np.uint8)
    owner = np.zeros((num_frames, height, width), np.int64)
    for t in range(num_frames):
        frame = np.zeros((height, width, 3), np.float32)
        for layer, (texture, mask) in enumerate(zip(textures, masks, strict=True)):
            colour = cv2.warpAffine(
                texture, maps[layer, t], (width, height), borderMode=cv2.BORDER_REFLECT
            )
            alpha = cv2.warpAffine(
                mask, maps[layer, t], (width, height), borderMode=cv2.BORDER_CONSTANT
            )
            frame += alpha[..., None] * (colour - frame)
            owner[t][alpha >= 0.5] = layer
        video[t] = frame.round().clip(0, 255).astype(np.uint8)

    layers, local = _sample_points(rng, owner, maps, config.num_points)
    point_maps = maps[layers]  # (N, T, 2, 3)
    tracks = np.einsum("ntij,nj->tni", point_maps[..., :2], local) + point_maps[..., 2].transpose(
        1, 0, 2
    )
    inside = (
        (tracks[..., 0] >= 0)
        & (tracks[..., 0] <= width - 1)
        & (tracks[..., 1] >= 0)
        & (tracks[..., 1] <= height - 1)
    )
    rows = tracks[..., 1].round().clip(0, height - 1).astype(int)
    cols = tracks[..., 0].round().clip(0, width - 1).astype(int)
    owns = owner[np.arange(num_frames)[:, None], rows, cols] == layers[None]
    return TrackingSample(video, tracks.astype(np.float32), inside & owns, "synthetic")


def write_dataset(
    out_dir: str | os.PathLike[str],
    num_videos: int,
    config: SyntheticConfig | None = None,
    seed: int = 0,
    first: int = 0,
    photos: Sequence[np.ndarray] | None = None,
    photo_prob: float = 0.8,
) -> list[Path]:
    """Writes videos ``first .. first + num_videos − 1`` as sequences ``<out_dir>/00000`` ...

    Video i is drawn from ``numpy.random.default_rng((seed, i))``: the same seed gives the
    same files, and a different seed (e.g. for a held-out set) gives different videos.
    ``photos`` and ``photo_prob`` are passed to `make_video` (the same photographs in the
    same order give the same files).
    """
    config = config or SyntheticConfig()
    folders = []
    for index in range(first, first + num_videos):
        sample = make_video(np.random.default_rng((seed, index)), config, photos, photo_prob)
        folders.append(write_sequence(Path(out_dir) / f"{index:05d}", sample))
    return folders
