"""Pixel checks of the track drawing on tiny synthetic frames."""

from __future__ import annotations

from itertools import combinations

import cv2
import numpy as np
import pytest

from taptr.viz.draw import (
    default_radius,
    draw_frame,
    draw_tracks,
    draw_trajectories,
    point_colors,
)

RED = np.array([[255, 0, 0]], np.uint8)
GREY = 60


def _video(num_frames: int, size: int = 32) -> np.ndarray:
    return np.full((num_frames, size, size, 3), GREY, np.uint8)


def _still(x: float, y: float, num_frames: int) -> np.ndarray:
    return np.tile(np.array([[[x, y]]], np.float32), (num_frames, 1, 1))


def _changed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(a.astype(int) - b).sum(axis=-1) > 0


def test_point_colors_follow_y():
    positions = np.array([[5.0, 30.0], [30.0, 10.0], [5.0, 10.0], [5.0, 20.0]])
    colors = point_colors(positions)
    assert colors.shape == (4, 3) and colors.dtype == np.uint8
    np.testing.assert_array_equal(colors[2], [255, 0, 0])  # the top-left point is red
    hues = cv2.cvtColor(colors[:, None], cv2.COLOR_RGB2HSV)[:, 0, 0]
    assert hues[2] < hues[1] < hues[3] < hues[0]  # top to bottom, ties left to right
    # With a fixed range the colours do not depend on the other points.
    fixed = point_colors(positions, y_range=(0, 99))
    np.testing.assert_array_equal(point_colors(positions[2:], y_range=(0, 99)), fixed[2:])
    assert tuple(fixed[0]) != (255, 0, 0)


def _lab_distances(colors: np.ndarray) -> list[float]:
    """CIE76 colour differences (ΔE) of every pair of (N, 3) uint8 RGB colours."""
    lab = cv2.cvtColor(colors[:, None].astype(np.float32) / 255, cv2.COLOR_RGB2LAB)[:, 0]
    return [float(np.linalg.norm(lab[i] - lab[j])) for i, j in combinations(range(len(lab)), 2)]


@pytest.mark.parametrize(
    "ys", [[0, 190, 200], [10, 150, 160], [100, 101, 102], [5, 5, 5], [200, 0, 100]]
)
def test_three_points_get_clearly_different_colours(ys):
    # ΔE > 100 between any two; the old rainbow over y gave 12 for y = 0, 190, 200
    positions = np.column_stack([np.arange(len(ys), dtype=float), ys])
    assert min(_lab_distances(point_colors(positions))) > 100


@pytest.mark.parametrize("count", [2, 4, 5, 6])
def test_a_few_points_get_far_apart_colours(count):
    rng = np.random.default_rng(count)
    positions = rng.uniform(0, 1, (count, 2)) * [640, 3]  # nearly one row of points
    assert min(_lab_distances(point_colors(positions))) > 45


def test_visible_point_is_a_filled_disc_of_its_colour():
    frame = _video(1)[0]
    out = draw_frame(frame, _still(10, 12, 1), np.ones((1, 1), bool), RED, radius=3)
    ys, xs = np.mgrid[:32, :32]
    inner = (xs - 10) ** 2 + (ys - 12) ** 2 <= 2**2
    assert (out[inner] == RED).all()
    assert not _changed(out, frame)[(xs - 10) ** 2 + (ys - 12) ** 2 > 4.5**2].any()
    assert (frame == GREY).all()  # the input is not drawn on


def test_occluded_point_is_a_ring_with_an_unchanged_centre():
    frame = _video(1)[0]
    out = draw_frame(frame, _still(16, 16, 1), np.zeros((1, 1), bool), RED, radius=4)
    np.testing.assert_array_equal(out[15:18, 15:18], frame[15:18, 15:18])
    for y, x in [(16, 20), (16, 12), (12, 16), (20, 16)]:  # on the ring, radius 4
        assert out[y, x, 0] > 200 and out[y, x, 1] < GREY


def test_points_appear_from_their_query_frame():
    video = _video(4)
    out = draw_tracks(
        video, _still(16, 16, 4), np.ones((4, 1), bool), query_frames=np.array([2]), colors=RED
    )
    np.testing.assert_array_equal(out[:2], video[:2])
    assert (out[2:, 16, 16] == RED).all()


def test_trail_fades_and_breaks_where_occluded():
    num_frames = 5
    tracks = np.zeros((num_frames, 1, 2), np.float32)
    tracks[:, 0, 0] = [4, 10, 16, 22, 28]  # moves right by 6 px per frame along y = 16
    tracks[:, 0, 1] = 16
    visible = np.ones((num_frames, 1), bool)
    out = draw_tracks(_video(num_frames), tracks, visible, colors=RED, trail_length=4, radius=1.5)
    last = out[-1, 16].astype(int)
    # Segment midpoints, oldest first: red increases with recency (opacity 1/4 ... 4/4).
    reds = [last[x, 0] for x in (7, 13, 19, 25)]
    assert reds == sorted(reds) and reds[0] < 140 and reds[-1] > 200
    visible[2, 0] = False  # occluded at x = 16: no segment into or out of it
    out = draw_tracks(_video(num_frames), tracks, visible, colors=RED, trail_length=4, radius=1.5)
    assert (out[-1, 16, 13] == GREY).all() and (out[-1, 16, 19] == GREY).all()
    assert out[-1, 16, 25, 0] > 200
    no_trail = draw_tracks(_video(num_frames), tracks, visible, colors=RED, trail_length=0)
    assert (no_trail[-1, 16, 25] == GREY).all()


def test_default_size_scales_with_the_image():
    small = draw_frame(_video(1, 64)[0], _still(32, 32, 1), np.ones((1, 1), bool), RED)
    large = draw_frame(_video(1, 512)[0], _still(256, 256, 1), np.ones((1, 1), bool), RED)
    assert default_radius(256, 512) == 2.0 and default_radius(8, 8) == 1.5
    assert _changed(large, _video(1, 512)[0]).sum() > 2 * _changed(small, _video(1, 64)[0]).sum()


def test_default_colours_come_from_query_positions():
    tracks = np.array([[[5, 2], [5, 30]], [[9, 30], [9, 2]]], np.float32)  # points swap rows
    out = draw_tracks(_video(2), tracks, np.ones((2, 2), bool), radius=2, trail_length=0)
    top, bottom = point_colors(tracks[0])
    np.testing.assert_array_equal(out[0, 2, 5], top)
    np.testing.assert_array_equal(out[1, 30, 9], top)  # point 0 keeps its colour
    np.testing.assert_array_equal(out[1, 2, 9], bottom)


def test_trajectories_show_the_whole_path_on_one_frame():
    tracks = np.zeros((6, 1, 2), np.float32)
    tracks[:, 0, 0] = np.linspace(4, 28, 6)
    tracks[:, 0, 1] = np.linspace(4, 28, 6)  # the diagonal
    frame = _video(1)[0]
    visible = np.ones((6, 1), bool)
    out = draw_trajectories(frame, tracks, visible, colors=RED, radius=2)
    assert (out[28, 28] == RED).all()  # the point at its last position
    assert all(out[i, i, 0] > GREY for i in range(4, 29))  # a line along the whole path
    assert (out[4, 28] == GREY).all() and (frame == GREY).all()
    later = draw_trajectories(frame, tracks, visible, query_frames=np.array([3]), colors=RED)
    assert (later[10, 10] == GREY).all() and later[22, 22, 0] > GREY  # from the query on


def test_non_finite_positions_and_no_points_draw_nothing():
    tracks = np.full((2, 1, 2), np.nan, np.float32)
    out = draw_tracks(_video(2), tracks, np.ones((2, 1), bool), colors=RED)
    np.testing.assert_array_equal(out, _video(2))
    empty = draw_tracks(_video(2), np.zeros((2, 0, 2)), np.zeros((2, 0), bool))
    np.testing.assert_array_equal(empty, _video(2))


def test_shape_errors():
    with pytest.raises(ValueError, match="tracks must be"):
        draw_tracks(_video(2), np.zeros((2, 3)), np.ones((2, 3), bool))
    with pytest.raises(ValueError, match="visible must be"):
        draw_tracks(_video(2), np.zeros((2, 3, 2)), np.ones((2, 4), bool))
    with pytest.raises(ValueError, match="frames"):
        draw_tracks(_video(3), np.zeros((2, 3, 2)), np.ones((2, 3), bool))
    with pytest.raises(ValueError, match="query_frames"):
        draw_tracks(_video(2), np.zeros((2, 3, 2)), np.ones((2, 3), bool), query_frames=[0, 0, 2])
