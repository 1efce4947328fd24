"""Region queries and overlay warping on a synthetic video with exactly known motion."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from taptr.api.regions import read_mask, sample_region_queries
from taptr.apps.editing import fit_region_transform, overlay_region
from tests.helpers import SHARED_MEDIA

SIZE = 96
GREEN = (0, 255, 0)


def _region() -> np.ndarray:
    mask = np.zeros((SIZE, SIZE), bool)
    mask[35:55, 30:60] = True  # pixels x 30..59, y 35..54: centre (44.5, 44.5)
    return mask


def _motion(t: int) -> np.ndarray:
    """(3, 3) similarity of frame 0 to frame t: rotation, zoom and shift about (44.5, 44.5)."""
    angle, scale, shift = 0.06 * t, 1 + 0.04 * t, np.array([2.0 * t, -1.5 * t])
    linear = scale * np.array(
        [[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]]
    )
    matrix = np.eye(3)
    matrix[:2, :2] = linear
    matrix[:2, 2] = np.array([44.5, 44.5]) + shift - linear @ [44.5, 44.5]
    return matrix


def _apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ matrix[:2, :2].T + matrix[:2, 2]


def _scene(num_frames: int = 5):
    """A textured rectangle moving by `_motion` over a grey background, with exact tracks."""
    rng = np.random.default_rng(0)
    texture = np.full((SIZE, SIZE, 3), 100, np.uint8)
    texture[_region()] = rng.integers(0, 256, (int(_region().sum()), 3)) // 2
    video = np.stack(
        [
            cv2.warpAffine(texture, _motion(t)[:2], (SIZE, SIZE), borderValue=(100, 100, 100))
            for t in range(num_frames)
        ]
    )
    points = sample_region_queries(_region(), 0, stride=4)[:, 1:]
    tracks = np.stack([_apply(_motion(t), points) for t in range(num_frames)]).astype(np.float32)
    return video, tracks, np.ones(tracks.shape[:2], bool)


def _coverage(edited: np.ndarray, original: np.ndarray) -> np.ndarray:
    """(H, W) estimated overlay alpha, from the green channel of a green overlay."""
    green, base = edited[..., 1].astype(float), original[..., 1].astype(float)
    return np.clip((green - base) / np.maximum(255 - base, 1), 0, 1)


def _centroid(weights: np.ndarray) -> np.ndarray:
    ys, xs = np.mgrid[: weights.shape[0], : weights.shape[1]]
    return np.array([(xs * weights).sum(), (ys * weights).sum()]) / weights.sum()


def test_region_queries_form_a_grid_inside_the_mask():
    queries = sample_region_queries(_region(), 7, stride=4)
    assert queries.dtype == np.float32 and (queries[:, 0] == 7).all()
    x, y = queries[:, 1].astype(int), queries[:, 2].astype(int)
    assert _region()[y, x].all()
    assert len(queries) == len(np.unique(x)) * len(np.unique(y)) == 8 * 5
    assert set(np.diff(np.unique(x))) == {4} and set(np.diff(np.unique(y))) == {4}
    # centred on the region: the margins left and right (and top and bottom) match
    assert abs((x.min() - 30) - (59 - x.max())) <= 1 and abs((y.min() - 35) - (54 - y.max())) <= 1


def test_region_queries_cap_and_tiny_regions():
    capped = sample_region_queries(_region(), 0, stride=2, max_points=10)
    full = sample_region_queries(_region(), 0, stride=2)
    assert len(capped) == 10 and len(full) > 100
    assert capped[0, 2] == full[0, 2] and capped[-1, 2] == full[-1, 2]  # spread over the region
    tiny = np.zeros((20, 20), bool)
    tiny[5:7, 8:10] = True
    np.testing.assert_array_equal(sample_region_queries(tiny, 0, stride=16)[:, 1:], [[8, 5]])
    with pytest.raises(ValueError, match="non-empty"):
        sample_region_queries(np.zeros((8, 8), bool), 0)


def test_fit_recovers_motion_and_drops_outliers():
    points = sample_region_queries(_region(), 0, stride=4)[:, 1:]
    target = _apply(_motion(3), points)
    target[::5] += 25.0  # every fifth point badly tracked
    fit = fit_region_transform(points, target)
    np.testing.assert_allclose(fit.matrix / fit.matrix[2, 2], _motion(3), atol=1e-3)
    np.testing.assert_array_equal(fit.inliers, np.arange(len(points)) % 5 != 0)
    few = fit_region_transform(points[:5], _apply(_motion(2), points[:5]))  # similarity fallback
    np.testing.assert_allclose(few.matrix, _motion(2), atol=1e-4)
    assert fit_region_transform(points[:2], points[:2]) is None


def test_overlay_follows_the_region():
    video, tracks, visible = _scene()
    overlay = np.zeros((10, 20, 3), np.uint8)
    overlay[:] = GREEN
    edited = overlay_region(video, overlay, _region(), tracks, visible, query_frame=0)
    assert edited.shape == video.shape and edited.dtype == np.uint8
    for t in range(len(video)):
        coverage = _coverage(edited[t], video[t])
        expected = _apply(_motion(t), np.array([44.5, 44.5]))
        assert np.linalg.norm(_centroid(coverage) - expected) < 1.0
        area = 30 * 20 * (1 + 0.04 * t) ** 2  # the region's area, zoomed
        assert abs(coverage.sum() - area) < 0.05 * area


def test_overlay_hidden_when_occluded():
    video, tracks, visible = _scene()
    visible[2] = False  # fully occluded
    visible[3, : int(0.6 * visible.shape[1])] = False  # most points occluded
    visible[4, :2] = False  # a few points occluded
    overlay = np.full((8, 8, 3), 255, np.uint8)
    edited = overlay_region(video, overlay, _region(), tracks, visible, query_frame=0)
    np.testing.assert_array_equal(edited[2:4], video[2:4])
    assert not np.array_equal(edited[4], video[4])


def test_occluded_points_cut_their_cells_out():
    video, tracks, visible = _scene(num_frames=1)
    visible[0, tracks[0, :, 0] < 44.5] = False  # the left half of the region is occluded
    overlay = np.zeros((4, 4, 3), np.uint8)
    overlay[:] = GREEN
    edited = overlay_region(video, overlay, _region(), tracks, visible, query_frame=0)
    coverage = _coverage(edited[0], video[0])
    assert coverage[35:55, 30:43].max() == 0 and coverage[37:53, 47:58].min() > 0.99


def test_alpha_and_opacity_blend():
    video, tracks, visible = _scene(num_frames=1)
    overlay = np.zeros((20, 30, 4), np.uint8)
    overlay[..., 1] = 255
    overlay[:, 15:, 3] = 255  # transparent left half, opaque right half
    edited = overlay_region(video, overlay, _region(), tracks, visible, 0, opacity=0.5)
    coverage = _coverage(edited[0], video[0])
    assert coverage[35:55, 30:44].max() < 0.02
    np.testing.assert_allclose(coverage[36:54, 46:59], 0.5, atol=0.02)


def test_overlay_input_errors(tmp_path):
    video, tracks, visible = _scene(num_frames=2)
    with pytest.raises(ValueError, match="overlay must be"):
        overlay_region(video, np.zeros((4, 4), np.uint8), _region(), tracks, visible, 0)
    with pytest.raises(ValueError, match="same T"):
        overlay_region(video, np.zeros((4, 4, 3), np.uint8), _region(), tracks[:1], visible, 0)
    cv2.imwrite(str(tmp_path / "mask.png"), _region().astype(np.uint8) * 255)
    np.testing.assert_array_equal(read_mask(tmp_path / "mask.png"), _region())
    with pytest.raises(FileNotFoundError):
        read_mask(tmp_path / "missing.png")


@pytest.mark.skipif(not SHARED_MEDIA.is_dir(), reason="shared sample media not present")
def test_shared_apple_mask_gives_queries_on_the_apple():
    mask = read_mask(SHARED_MEDIA / "apple_mask.png")
    assert mask.shape == (720, 1296) and 0 < mask.mean() < 0.5
    queries = sample_region_queries(mask, 0, stride=16, max_points=200)
    assert 20 < len(queries) <= 200
    assert mask[queries[:, 2].astype(int), queries[:, 1].astype(int)].all()


def test_edit_twice_writes_the_same_file(tmp_path):
    """`taptr edit` is reproducible: two runs give the same bytes (issue 30, item 3)."""
    import torch

    import taptr
    from taptr.cli.main import main
    from taptr.io.video import write_video

    photos = pytest.importorskip("taptr.data.photos")
    pytest.importorskip("sklearn", reason="the photographs come with scikit-learn")
    photo = photos.load_builtin_photos("train")[0]
    # a hand-held camera over a photograph: real texture, which plain noise does not give
    frames = [
        cv2.warpAffine(photo, np.array([[1 + 0.01 * t, 0, -3 * t], [0, 1, -2 * t]]), (320, 240))
        for t in range(12)
    ]
    clip = write_video(tmp_path / "clip.mp4", frames, fps=10)
    mask = np.zeros((240, 320), np.uint8)
    mask[60:160, 80:220] = 255
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    logo = np.zeros((16, 16, 4), np.uint8)
    logo[::2, ::2] = (0, 0, 255, 200)  # a semi-transparent checkerboard: every blend shows
    cv2.imwrite(str(tmp_path / "logo.png"), logo)
    torch.manual_seed(0)
    checkpoint = taptr.save_checkpoint(taptr.build_model("tiny"), tmp_path / "tiny.pth")
    argv = ["edit", str(clip), "--mask", str(tmp_path / "mask.png"), "--stride", "10"]
    argv += ["--overlay", str(tmp_path / "logo.png"), "--checkpoint", str(checkpoint)]
    for name in ("one.mp4", "two.mp4"):
        assert main([*argv, "--out", str(tmp_path / name)]) == 0
    assert (tmp_path / "one.mp4").read_bytes() == (tmp_path / "two.mp4").read_bytes()
