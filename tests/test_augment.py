"""Augmentations keep tracks on the pixels they follow, and occluders hide points."""

from __future__ import annotations

import numpy as np
import pytest

from taptr.data import augment
from taptr.data.augment_spatial import flip, pan_and_crop, random_flip, resize
from taptr.types import TrackingSample

HEIGHT, WIDTH, FRAMES, POINTS = 48, 64, 4, 200


def _ramp_clip(seed: int = 0) -> TrackingSample:
    """Colour = linear function of the pixel position, so bilinear sampling is exact:
    R = 4x, G = 5y, B = 40t. Points sit at random places, different on every frame."""
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    frames = []
    for t in range(FRAMES):
        frames.append(np.stack([4 * x, 5 * y, np.full_like(x, 40 * t)], -1).astype(np.uint8))
    rng = np.random.default_rng(seed)
    tracks = rng.uniform([1, 1], [WIDTH - 2, HEIGHT - 2], (FRAMES, POINTS, 2)).astype(np.float32)
    return TrackingSample(np.stack(frames), tracks, np.ones((FRAMES, POINTS), bool))


def _bilinear(frame: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(H, W, C) frame at (N, 2) (x, y) pixel-centre positions, (N, C)."""
    x, y = points[:, 0], points[:, 1]
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    f = frame.astype(np.float64)
    x1, y1 = np.minimum(x0 + 1, frame.shape[1] - 1), np.minimum(y0 + 1, frame.shape[0] - 1)
    top = f[y0, x0] * (1 - fx) + f[y0, x1] * fx
    bottom = f[y1, x0] * (1 - fx) + f[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def _position_error(original: TrackingSample, moved: TrackingSample) -> np.ndarray:
    """How far (in original pixels) each visible moved track is from where it came from."""
    errors = []
    for t in range(FRAMES):
        keep = moved.visible[t]
        colour = _bilinear(moved.video[t], moved.tracks[t, keep])
        seen_xy = colour[:, :2] / (4, 5)  # invert the ramp
        errors.append(np.abs(seen_xy - original.tracks[t, keep]).max(axis=1))
    return np.concatenate(errors)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pan_and_crop_moves_tracks_with_pixels(seed):
    clip = _ramp_clip(seed)
    out = pan_and_crop(clip, np.random.default_rng(seed), (40, 40), pad_bounds=(0, 5))
    assert out.video.shape == (FRAMES, 40, 40, 3)
    assert out.visible.sum() > POINTS  # a good share of the points stays in the crop
    assert _position_error(clip, out).max() < 0.35  # uint8 rounding of the ramp
    # outside the crop means not visible
    inside = (out.tracks >= 0).all(-1) & (out.tracks[..., 0] <= 39) & (out.tracks[..., 1] <= 39)
    assert not (out.visible & ~inside).any()
    # the camera moves: the map is not the same on every frame
    shifts = out.tracks - clip.tracks
    assert np.ptp(shifts[:, 0, 0]) > 0 or np.ptp(shifts[:, 0, 1]) > 0


@pytest.mark.parametrize("horizontal,vertical", [(True, False), (False, True), (True, True)])
def test_flips_mirror_pixels_and_tracks(horizontal, vertical):
    clip = _ramp_clip()
    out = flip(clip, horizontal, vertical)
    twice = flip(out, horizontal, vertical)
    np.testing.assert_array_equal(twice.video, clip.video)
    np.testing.assert_allclose(twice.tracks, clip.tracks, atol=1e-5)
    assert _position_error(clip, out).max() < 1e-3


def test_random_flip_probabilities():
    clip = _ramp_clip()
    kept = random_flip(clip, np.random.default_rng(0), 0.0, 0.0)
    np.testing.assert_array_equal(kept.video, clip.video)
    mirrored = random_flip(clip, np.random.default_rng(0), 1.0, 0.0)
    np.testing.assert_array_equal(mirrored.video, clip.video[:, :, ::-1])


@pytest.mark.parametrize("size", [(24, 32), (72, 96), (30, 50)])
def test_resize_moves_tracks_with_pixels(size):
    clip = _ramp_clip()
    out = resize(clip, size)
    assert out.video.shape[1:3] == size
    assert _position_error(clip, out).max() < 0.5
    assert resize(clip, (HEIGHT, WIDTH)) is clip


@pytest.mark.parametrize("occluder", [augment.erase, augment.replace])
def test_occluders_hide_the_points_they_cover(occluder):
    clip = _ramp_clip()
    out = occluder(clip, np.random.default_rng(3), prob=1.0)
    np.testing.assert_array_equal(out.video[0], clip.video[0])  # the query frame is kept
    np.testing.assert_array_equal(out.tracks, clip.tracks)
    changed = (out.video != clip.video).any(-1)  # (T, H, W)
    pixel = np.round(clip.tracks).astype(int)
    under = changed[np.arange(FRAMES)[:, None], pixel[..., 1], pixel[..., 0]]
    assert under.any() and not (out.visible & under).any()  # a visible point's pixel is intact
    assert (~out.visible[1:]).sum() >= under.sum()
    assert clip.visible.all()  # the input is not modified


def test_covered_uses_the_pixel_that_contains_the_point():
    points = np.array([[1.49, 2.0], [1.51, 2.0], [4.49, 2.0], [4.51, 2.0]])
    # pixels x = 2..4, y = 0..3
    assert augment.covered(points, (2, 0, 5, 4)).tolist() == [False, True, True, False]


@pytest.mark.parametrize("change", [augment.jitter_colour, augment.blur])
def test_photometric_changes_keep_tracks(change):
    clip = _ramp_clip()
    out = change(clip, np.random.default_rng(0), prob=1.0)
    assert out.video.shape == clip.video.shape and out.video.dtype == np.uint8
    assert not np.array_equal(out.video, clip.video)
    np.testing.assert_array_equal(out.tracks, clip.tracks)
    np.testing.assert_array_equal(out.visible, clip.visible)
    assert change(clip, np.random.default_rng(0), prob=0.0) is clip


def test_colour_jitter_draws_every_frame_independently():
    clip = _ramp_clip()
    same = TrackingSample(np.repeat(clip.video[:1], FRAMES, 0), clip.tracks, clip.visible)
    out = augment.jitter_colour(same, np.random.default_rng(0), prob=1.0)
    assert not np.array_equal(out.video[0], out.video[1])


def test_mark_outside():
    clip = _ramp_clip()
    tracks = clip.tracks.copy()
    tracks[0, 0] = (-0.01, 5)
    tracks[0, 1] = (WIDTH - 1, HEIGHT - 1)  # the last pixel centre is inside
    tracks[0, 2] = (5, HEIGHT - 0.99)
    out = augment.mark_outside(TrackingSample(clip.video, tracks, clip.visible))
    assert out.visible[0, :3].tolist() == [False, True, False]
