"""A real-photo tracking benchmark with exact ground truth, in TAP-Vid DAVIS format.

Each video shows held-out photographs (by default the ``heldout`` split of
`taptr.data.photos`, never used for training data) moved by known smooth warps:

* a background: a crop of a photograph seen through a smoothly moving camera, one
  homography per frame (drift, a slow sinusoidal sway, rotation, zoom and a little
  perspective);
* one or more foreground layers: other crops of photographs, cut out by a random shape and
  moved by their own smooth similarity transforms;
* an occluder in front of everything: a procedural or flat-coloured shape that sweeps across
  the frame, hiding points and then revealing them again.

Layer pixels are warped with OpenCV (pixel centres at integers), and a point on a layer
moves by exactly that layer's map, so tracks are exact. A point is visible where its own
layer owns its pixel (mask ≥ 0.5) and it lies inside the frame. Points are drawn at random
pixels of random frames on the photographs (never on the occluder), like TAP-Vid's
annotations, which mark points on real surfaces.

`write_photo_bench` writes a pickle ``{name: {"video", "points", "occluded"}}`` with
(T, H, W, 3) uint8 frames, (N, T, 2) normalised raster points and (N, T) occlusion flags, so
``taptr eval --dataset davis --root FILE`` scores any tracker on it.
"""

from __future__ import annotations

import os
import pickle
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from taptr.data.photos import photo_texture
from taptr.data.synthetic import _shape_mask, _texture
from taptr.data.tapvid import pixels_to_raster
from taptr.types import TrackingSample


@dataclass(frozen=True)
class PhotoBenchConfig:
    """Size and motion of the benchmark videos.

    Attributes:
        height: frame height H in pixels (TAP-Vid's evaluation size is 256).
        width: frame width W in pixels.
        num_frames: frames T per video.
        num_points: tracks N per video.
        foreground: (min, max) number of moving photograph layers.
        camera_drift: largest camera drift over the whole video, in pixels.
        object_drift: largest foreground drift over the whole video, in pixels.
    """

    height: int = 256
    width: int = 256
    num_frames: int = 24
    num_points: int = 256
    foreground: tuple[int, int] = (1, 2)
    camera_drift: float = 48.0
    object_drift: float = 64.0

    def __post_init__(self) -> None:
        if min(self.height, self.width) < 32 or self.num_frames < 2 or self.num_points < 1:
            raise ValueError("need frames of at least 32×32 pixels, two frames and one point")
        if not 0 <= self.foreground[0] <= self.foreground[1]:
            raise ValueError(f"foreground must be (min, max), got {self.foreground}")


def _smooth_path(rng: np.random.Generator, num_frames: int, amplitude: float) -> np.ndarray:
    """(T,) a smooth 1-D motion starting at 0: a linear drift plus a slow sinusoidal sway."""
    time = np.arange(num_frames) / max(num_frames - 1, 1)  # 0 … 1
    drift = rng.uniform(-1, 1) * amplitude * time
    period = rng.uniform(0.6, 1.5)
    phase = rng.uniform(0, 2 * np.pi)
    sway = 0.35 * amplitude * rng.uniform(-1, 1) * (np.sin(2 * np.pi * time / period + phase))
    return drift + sway - sway[0]


def _similarity(
    center_to: np.ndarray, angle: float, scale: float, center_from: np.ndarray
) -> np.ndarray:
    """3×3 map sending ``center_from`` to ``center_to``, rotating and scaling about it."""
    cos, sin = scale * np.cos(angle), scale * np.sin(angle)
    linear = np.array([[cos, -sin], [sin, cos]])
    matrix = np.eye(3)
    matrix[:2, :2] = linear
    matrix[:2, 2] = center_to - linear @ center_from
    return matrix


def _camera_homographies(
    rng: np.random.Generator, config: PhotoBenchConfig, canvas: int
) -> np.ndarray:
    """(T, 3, 3) maps from background-canvas pixels to frame pixels."""
    num_frames = config.num_frames
    shift = np.stack([_smooth_path(rng, num_frames, config.camera_drift) for _ in range(2)], -1)
    angle = _smooth_path(rng, num_frames, 0.15)
    zoom = 1 + _smooth_path(rng, num_frames, 0.15)
    tilt = np.stack([_smooth_path(rng, num_frames, 2.5e-4) for _ in range(2)], -1)  # perspective
    frame_center = np.array([config.width - 1, config.height - 1]) / 2
    canvas_center = np.full(2, (canvas - 1) / 2)
    maps = []
    for t in range(num_frames):
        similarity = _similarity(frame_center, angle[t], zoom[t], canvas_center + shift[t])
        # perspective about the frame centre: points there do not move, the edges foreshorten
        perspective = np.eye(3)
        perspective[2, :2] = tilt[t]
        perspective[2, 2] = 1 - tilt[t] @ frame_center
        to_center = np.eye(3)
        to_center[:2, 2] = -frame_center
        back = np.eye(3)
        back[:2, 2] = frame_center
        maps.append(back @ perspective @ to_center @ similarity)
    stacked = np.stack(maps)
    return stacked / stacked[:, 2:3, 2:3]


def _object_homographies(
    rng: np.random.Generator, config: PhotoBenchConfig, size: int
) -> np.ndarray:
    """(T, 3, 3) maps from a foreground patch's pixels to frame pixels."""
    num_frames = config.num_frames
    frame = np.array([config.width, config.height], np.float64)
    start = rng.uniform(0.15 * frame, 0.85 * frame)
    shift = np.stack([_smooth_path(rng, num_frames, config.object_drift) for _ in range(2)], -1)
    angle = rng.uniform(-0.3, 0.3) + _smooth_path(rng, num_frames, 0.5)
    scale = rng.uniform(0.85, 1.15) * (1 + _smooth_path(rng, num_frames, 0.2))
    patch_center = np.full(2, (size - 1) / 2)
    return np.stack(
        [_similarity(start + shift[t], angle[t], scale[t], patch_center) for t in range(num_frames)]
    )


def _occluder_homographies(
    rng: np.random.Generator, config: PhotoBenchConfig, size: int
) -> np.ndarray:
    """(T, 3, 3) maps of an occluder that crosses the frame from one side to the other."""
    num_frames = config.num_frames
    frame = np.array([config.width, config.height], np.float64)
    # enter and leave through opposite sides, so it passes over the middle of the video
    direction = rng.uniform(0, 2 * np.pi)
    unit = np.array([np.cos(direction), np.sin(direction)])
    reach = 0.5 * (np.abs(unit) @ frame) + 0.25 * size
    center = frame / 2 + rng.uniform(-0.2, 0.2, 2) * frame
    time = np.linspace(-1, 1, num_frames) * rng.uniform(0.8, 1.2)
    angle = rng.uniform(0, 2 * np.pi) + rng.uniform(-0.3, 0.3) * time
    patch_center = np.full(2, (size - 1) / 2)
    return np.stack(
        [
            _similarity(center + unit * reach * time[t], angle[t], 1.0, patch_center)
            for t in range(num_frames)
        ]
    )


def _apply(maps: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Applies per-point (N, T, 3, 3) homographies to (N, 2) points: (T, N, 2)."""
    homogeneous = np.concatenate([points, np.ones((points.shape[0], 1))], -1)
    mapped = np.einsum("ntij,nj->tni", maps, homogeneous)
    return mapped[..., :2] / mapped[..., 2:3]


def make_photo_video(
    rng: np.random.Generator, photos: Sequence[np.ndarray], config: PhotoBenchConfig
) -> TrackingSample:
    """Renders one benchmark video with its exact tracks.

    Args:
        rng: the only source of randomness.
        photos: the photographs to show, each (h, w, 3) uint8 RGB.
        config: sizes and motion.

    Returns:
        video (T, H, W, 3) uint8 RGB, tracks (T, N, 2) float32 pixels, visible (T, N) bool.
    """
    if not photos:
        raise ValueError("the photo benchmark needs at least one photograph")
    height, width, num_frames = config.height, config.width, config.num_frames
    # the canvas covers the frame under the largest drift, zoom-out and tilt of the camera
    canvas = int(1.6 * max(height, width) + 2 * config.camera_drift)
    textures = [photo_texture(rng, photos, canvas, canvas, crop=(0.7, 1.0), jitter=0.1)]
    masks = [np.ones((canvas, canvas), np.float32)]
    maps = [_camera_homographies(rng, config, canvas)]
    for _ in range(int(rng.integers(config.foreground[0], config.foreground[1] + 1))):
        size = int(min(height, width) * rng.uniform(0.35, 0.6))
        textures.append(photo_texture(rng, photos, size, size, crop=(0.25, 0.6), jitter=0.1))
        masks.append(_shape_mask(rng, size))
        maps.append(_object_homographies(rng, config, size))
    tracked_layers = len(textures)
    # the occluder: flat colour or procedural texture, never a photograph, never tracked
    size = int(min(height, width) * rng.uniform(0.25, 0.4))
    if rng.random() < 0.5:
        occluder = np.empty((size, size, 3), np.uint8)
        occluder[:] = rng.integers(0, 256, 3).astype(np.uint8)
    else:
        occluder = _texture(rng, size, size)
    textures.append(occluder)
    masks.append(_shape_mask(rng, size))
    maps.append(_occluder_homographies(rng, config, size))
    layer_maps = np.stack(maps)  # (layers, T, 3, 3), back to front

    video = np.zeros((num_frames, height, width, 3), np.uint8)
    owner = np.zeros((num_frames, height, width), np.int64)
    for t in range(num_frames):
        frame = np.zeros((height, width, 3), np.float32)
        for layer, (texture, mask) in enumerate(zip(textures, masks, strict=True)):
            matrix = layer_maps[layer, t]
            colour = cv2.warpPerspective(
                texture.astype(np.float32), matrix, (width, height), borderMode=cv2.BORDER_REFLECT
            )
            alpha = cv2.warpPerspective(
                mask, matrix, (width, height), borderMode=cv2.BORDER_CONSTANT
            )
            frame += alpha[..., None] * (colour - frame)
            owner[t][alpha >= 0.5] = layer
        video[t] = frame.round().clip(0, 255).astype(np.uint8)

    layers, local = _sample_on_photos(rng, owner, layer_maps, tracked_layers, config.num_points)
    tracks = _apply(layer_maps[layers], local)  # (T, N, 2)
    inside = (
        (tracks[..., 0] >= 0)
        & (tracks[..., 0] <= width - 1)
        & (tracks[..., 1] >= 0)
        & (tracks[..., 1] <= height - 1)
    )
    rows = tracks[..., 1].round().clip(0, height - 1).astype(int)
    cols = tracks[..., 0].round().clip(0, width - 1).astype(int)
    owns = owner[np.arange(num_frames)[:, None], rows, cols] == layers[None]
    return TrackingSample(video, tracks.astype(np.float32), inside & owns, "photo")


def _sample_on_photos(
    rng: np.random.Generator,
    owner: np.ndarray,
    layer_maps: np.ndarray,
    tracked_layers: int,
    num_points: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Random pixels of random frames on the photograph layers, lifted to layer pixels.

    Returns:
        layer index of each point (N,) and its position in that layer's own pixels (N, 2).
    """
    num_frames, height, width = owner.shape
    chosen_layers, chosen_xy, chosen_frames = [], [], []
    needed = num_points
    while needed > 0:
        # a quarter of the frame at most is the occluder: 2N candidates nearly always do
        frames = rng.integers(0, num_frames, 2 * needed)
        xy = rng.uniform([0, 0], [width - 1, height - 1], (2 * needed, 2))
        layers = owner[frames, xy[:, 1].round().astype(int), xy[:, 0].round().astype(int)]
        keep = np.flatnonzero(layers < tracked_layers)[:needed]
        chosen_layers.append(layers[keep])
        chosen_xy.append(xy[keep])
        chosen_frames.append(frames[keep])
        needed -= keep.size
    layers = np.concatenate(chosen_layers)
    xy = np.concatenate(chosen_xy)
    frames = np.concatenate(chosen_frames)
    inverse = np.linalg.inv(layer_maps[layers, frames])  # (N, 3, 3) frame → layer
    homogeneous = np.concatenate([xy, np.ones((num_points, 1))], -1)
    local = np.einsum("nij,nj->ni", inverse, homogeneous)
    return layers, local[:, :2] / local[:, 2:3]


def sample_to_tapvid(sample: TrackingSample) -> dict[str, np.ndarray]:
    """A `TrackingSample` as a TAP-Vid item: video, (N, T, 2) raster points, (N, T) occluded."""
    height, width = sample.video.shape[1:3]
    points = pixels_to_raster(sample.tracks.transpose(1, 0, 2), height, width)
    return {
        "video": np.ascontiguousarray(sample.video),
        "points": points.astype(np.float32),
        "occluded": np.ascontiguousarray(~sample.visible.T),
    }


def write_photo_bench(
    out: str | os.PathLike[str],
    num_videos: int,
    photos: Sequence[np.ndarray],
    config: PhotoBenchConfig | None = None,
    seed: int = 0,
) -> Path:
    """Writes a TAP-Vid DAVIS-format pickle of ``num_videos`` benchmark videos.

    Video i is drawn from ``numpy.random.default_rng((seed, i))`` and named ``photo_{i:03d}``;
    the same photographs (in the same order), config and seed give the same file.

    Args:
        out: the pickle file to write (its folder is created).
        num_videos: number of videos.
        photos: the photographs, each (h, w, 3) uint8 RGB; use held-out ones.
        config: sizes and motion (default `PhotoBenchConfig()`).
        seed: the seed of the set.

    Returns:
        the path written.
    """
    if num_videos < 1:
        raise ValueError("num_videos must be at least 1")
    config = config or PhotoBenchConfig()
    items = {
        f"photo_{index:03d}": sample_to_tapvid(
            make_photo_video(np.random.default_rng((seed, index)), photos, config)
        )
        for index in range(num_videos)
    }
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    with open(partial, "wb") as file:
        pickle.dump(items, file, protocol=4)
    os.replace(partial, path)  # atomic: a reader never sees half a file
    return path
