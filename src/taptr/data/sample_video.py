"""A licence-clean sample clip with exact ground truth, made entirely by this package.

The scene is procedural, so no data file ships and nothing is downloaded: a flat textured
background (smooth colour fields, a few hundred antialiased shapes and a fine grain) seen by a
camera that pans, zooms in and rolls smoothly, and a textured disc in front of it that rolls
across the view and occludes the background as it passes. Both motions are known exactly,
so `SampleClip.track` gives the true tracks and visibility of any query.

Everything is drawn from one seeded generator, so the same arguments give the same frames.
Coordinates are (x, y) pixels with pixel centres at integers (also OpenCV's warp convention).
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from taptr.io.video import write_video


@dataclass(frozen=True)
class SampleClip:
    """A rendered clip and the motions that made it.

    Attributes:
        video: (T, H, W, 3) uint8 RGB frames.
        camera: (T, 3, 3) float64; ``camera[t]`` maps (x, y, 1) background pixels of the
            scene texture to pixels of frame t (a similarity).
        disc: (T, 3, 3) float64; ``disc[t]`` maps (x, y, 1) pixels of the disc's texture to
            pixels of frame t (a rotation and a shift).
        disc_radius: radius of the occluding disc in pixels; its centre on frame t is
            ``disc[t] @ (r, r, 1)`` with r = ``disc_radius``.
        fps: frames per second the clip is meant to play at.
    """

    video: np.ndarray
    camera: np.ndarray
    disc: np.ndarray
    disc_radius: float
    fps: float

    def disc_centers(self) -> np.ndarray:
        """(T, 2) (x, y) pixel centre of the occluding disc on each frame."""
        return self.disc[:, :2, :2] @ np.full(2, self.disc_radius) + self.disc[:, :2, 2]

    def track(self, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The true tracks and visibility of query points.

        A query inside the disc on its query frame moves with the disc; any other query
        moves with the background and is occluded while the disc covers it. A point is also
        invisible while it is outside the frame.

        Args:
            queries: (N, 3) (t, x, y), t an integer frame index, (x, y) pixels.

        Returns:
            tracks: (T, N, 2) float32 (x, y) pixels.
            visible: (T, N) bool, True where the point is visible.
        """
        queries = np.asarray(queries, dtype=np.float64).reshape(-1, 3)
        frames = queries[:, 0].astype(np.int64)
        if frames.size and not (0 <= frames.min() <= frames.max() < len(self.video)):
            raise ValueError(f"query frames must lie in [0, {len(self.video) - 1}]")
        points = np.column_stack([queries[:, 1:], np.ones(len(queries))])  # (N, 3)
        centers = self.disc_centers()
        on_disc = np.linalg.norm(queries[:, 1:] - centers[frames], axis=1) <= self.disc_radius
        motion = np.where(on_disc[:, None, None], self.disc[frames], self.camera[frames])
        # Back to texture coordinates on the query frame, then forward to every frame.
        texture = np.einsum("nij,nj->ni", np.linalg.inv(motion), points)  # (N, 3)
        forward = np.where(on_disc[None, :, None, None], self.disc[:, None], self.camera[:, None])
        tracks = np.einsum("tnij,nj->tni", forward, texture)[..., :2]  # (T, N, 2)
        height, width = self.video.shape[1:3]
        inside = ((tracks >= -0.5) & (tracks <= np.array([width, height]) - 0.5)).all(axis=-1)
        covered = np.linalg.norm(tracks - centers[:, None], axis=-1) <= self.disc_radius
        return tracks.astype(np.float32), inside & (on_disc[None] | ~covered)


def make_sample_clip(
    *, num_frames: int = 48, height: int = 256, width: int = 256, fps: float = 24.0, seed: int = 0
) -> SampleClip:
    """Renders the sample clip.

    Args:
        num_frames: number of frames T, >= 2.
        height: frame height H in pixels.
        width: frame width W in pixels.
        fps: frames per second stored with the clip.
        seed: seed of the scene's textures.

    Returns:
        The clip with its camera and disc motions.
    """
    scene = _Scene.make(num_frames, height, width, seed)
    video = np.stack(list(scene.frames()))
    return SampleClip(video, scene.camera, scene.disc, scene.radius, fps)


def write_sample_video(
    path: str | os.PathLike[str],
    *,
    num_frames: int = 48,
    height: int = 256,
    width: int = 256,
    seed: int = 0,
) -> Path:
    """Writes the sample clip (by default 48 frames, 256 × 256) as a 24 fps H.264 mp4.

    Frames are rendered as they are encoded, so a long clip is never held in memory. The
    frames are those of `make_sample_clip` with the same arguments.

    Args:
        path: the ``.mp4`` file to write.
        num_frames: number of frames T, >= 2.
        height: frame height H in pixels, >= 16 (an odd side is padded by one pixel).
        width: frame width W in pixels, >= 16.
        seed: seed of the scene's textures.
    """
    scene = _Scene.make(num_frames, height, width, seed)
    return write_video(path, scene.frames(), SAMPLE_FPS)


SAMPLE_FPS = 24.0
"""Frames per second of the written sample clip."""


@dataclass(frozen=True)
class _Scene:
    """The textures and motions of a clip, from which each frame is rendered on demand.

    Attributes:
        texture: (2H, 2W, 3) uint8 scene the camera looks at.
        disc_texture: (S, S, 3) uint8 texture of the disc; disc_alpha: (S, S) float32
            coverage of its antialiased edge.
        camera, disc: (T, 3, 3) float64 motions (see `SampleClip`); radius: the disc's.
    """

    texture: np.ndarray
    disc_texture: np.ndarray
    disc_alpha: np.ndarray
    camera: np.ndarray
    disc: np.ndarray
    radius: float

    @classmethod
    def make(cls, num_frames: int, height: int, width: int, seed: int) -> _Scene:
        """The scene of a clip of this length and size (one seeded generator draws it).

        Raises:
            ValueError: fewer than 2 frames, or a side under 16 pixels.
        """
        if num_frames < 2 or min(height, width) < 16:
            raise ValueError(
                f"need >= 2 frames of at least 16x16, got {num_frames} of {width}x{height}"
            )
        rng = np.random.default_rng(seed)
        texture = _texture(rng, 2 * height, 2 * width)
        radius = 0.16 * min(height, width)
        side = math.ceil(2 * radius) + 1
        disc_texture = _texture(rng, side, side)
        disc_mask = np.zeros((side, side), np.uint8)  # OpenCV antialiases 8-bit images only
        cv2.circle(disc_mask, _fixed((radius, radius)), round(radius * 16), 255, -1, cv2.LINE_AA, 4)
        progress = np.linspace(0.0, 1.0, num_frames)
        camera = np.stack([_camera(p, height, width) for p in progress])
        disc = np.stack([_disc_motion(p, radius, height, width) for p in progress])
        alpha = disc_mask.astype(np.float32) / 255
        return cls(texture, disc_texture, alpha, camera, disc, radius)

    def frames(self) -> Iterator[np.ndarray]:
        """The (H, W, 3) uint8 RGB frames in order, each rendered when asked for."""
        height, width = self.texture.shape[0] // 2, self.texture.shape[1] // 2
        for camera_t, disc_t in zip(self.camera, self.disc, strict=True):
            background = cv2.warpAffine(
                self.texture,
                camera_t[:2],
                (width, height),
                flags=cv2.INTER_CUBIC,
                borderMode=cv2.BORDER_REFLECT,
            )
            front = cv2.warpAffine(
                self.disc_texture, disc_t[:2], (width, height), flags=cv2.INTER_CUBIC
            )
            alpha = cv2.warpAffine(
                self.disc_alpha, disc_t[:2], (width, height), flags=cv2.INTER_LINEAR
            )
            blend = background * (1 - alpha[..., None]) + front * alpha[..., None]
            yield np.clip(np.round(blend), 0, 255).astype(np.uint8)


def _camera(progress: float, height: int, width: int) -> np.ndarray:
    """(3, 3) scene-to-frame similarity at ``progress`` ∈ [0, 1] of the clip."""
    ease = 0.5 - 0.5 * math.cos(math.pi * progress)  # starts and stops smoothly
    scale = 1.0 + 0.25 * ease
    angle = math.radians(10.0 * ease)
    # The view centre in scene pixels; the scene is twice the frame size, centred on it.
    center = np.array([width - 0.5, height - 0.5]) + np.array(
        [width * (0.15 * ease - 0.05), height * 0.1 * math.sin(math.pi * progress)]
    )
    frame_center = np.array([(width - 1) / 2, (height - 1) / 2])
    return _similarity(scale, angle, center, frame_center)


def _disc_motion(progress: float, radius: float, height: int, width: int) -> np.ndarray:
    """(3, 3) disc-texture-to-frame rigid motion: rolling left to right along an arc."""
    center = np.array(
        [width * (0.1 + 0.8 * progress), height * (0.65 - 0.1 * math.sin(math.pi * progress))]
    )
    angle = (0.8 * width / radius) * progress  # rolling without slipping
    return _similarity(1.0, angle, np.array([radius, radius]), center)


def _similarity(scale: float, angle: float, source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(3, 3) rotation by ``angle`` and scaling about ``source``, which goes to ``target``."""
    cos, sin = scale * math.cos(angle), scale * math.sin(angle)
    linear = np.array([[cos, -sin], [sin, cos]])
    matrix = np.eye(3)
    matrix[:2, :2] = linear
    matrix[:2, 2] = target - linear @ source
    return matrix


def _texture(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """(H, W, 3) uint8 RGB: smooth colour fields, antialiased shapes and a fine grain."""
    coarse = rng.uniform(40, 215, (4, 4, 3)).astype(np.float32)
    medium = rng.normal(0, 30, (max(2, height // 24), max(2, width // 24), 3)).astype(np.float32)
    field = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC) + cv2.resize(
        medium, (width, height), interpolation=cv2.INTER_CUBIC
    )
    canvas = np.ascontiguousarray(np.clip(field, 0, 255).astype(np.uint8))
    for _ in range(height * width // 900):
        center = rng.uniform(0, [width, height])
        size = rng.uniform(3, 0.06 * min(height, width) + 4)
        color = tuple(int(c) for c in rng.integers(0, 256, 3))
        kind = rng.integers(3)
        if kind == 0:
            cv2.circle(canvas, _fixed(center), round(size * 16), color, -1, cv2.LINE_AA, 4)
        else:
            corners = 3 if kind == 1 else 4
            angles = rng.uniform(0, 2 * math.pi) + np.linspace(0, 2 * math.pi, corners + 1)[:-1]
            angles += rng.uniform(-0.4, 0.4, corners)  # irregular, so corners are distinctive
            polygon = center + size * np.column_stack([np.cos(angles), np.sin(angles)])
            cv2.fillPoly(canvas, [np.round(polygon * 16).astype(np.int32)], color, cv2.LINE_AA, 4)
        if rng.random() < 0.5:
            cv2.circle(
                canvas, _fixed(center), round(size * 0.4 * 16), (20, 20, 20), 1, cv2.LINE_AA, 4
            )
    grain = rng.normal(0, 3, canvas.shape)  # faint: H.264 would smear a strong grain anyway
    return np.clip(canvas + grain, 0, 255).astype(np.uint8)


def _fixed(point: tuple[float, float] | np.ndarray) -> tuple[int, int]:
    """(x, y) pixels to OpenCV's 4-bit fixed-point drawing coordinates."""
    return round(float(point[0]) * 16), round(float(point[1]) * 16)
