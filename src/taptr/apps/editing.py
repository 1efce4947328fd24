"""Region editing: query points inside a mask, and an overlay image that follows the region.

The workflow behind ``taptr edit``:

1. `sample_region_queries` (`taptr.api.regions`, where the queries of a region are built)
   turns a boolean mask drawn on one frame (the query frame) into (t, x, y) queries on a
   regular pixel grid inside the region;
2. the tracker tracks them through the video;
3. `overlay_region` pastes an image onto the region in every frame: per frame it fits a
   homography (RANSAC, so wrongly tracked points are dropped as outliers) from the points'
   query positions to their tracked positions, and warps the overlay and the region mask
   with it. `apply_overlay` does the same for one frame, for streaming.

Occlusion is handled at two levels. A frame where fewer than ``min_visible_fraction`` of the
points are visible shows no overlay at all. Otherwise every pixel of the region belongs to
the cell of its nearest query point (a Voronoi partition of the region on the query frame),
and the cells of occluded points are cut out of the overlay, so an occluder in front of part
of the region stays in front.

Coordinates are (x, y) pixels with pixel centres at integers (OpenCV's convention as well);
masks are (H, W) bool, True inside the region; frames are (H, W, 3) uint8 RGB.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

# re-exported: the region's query points are part of this workflow's interface
from taptr.api.regions import read_mask as read_mask
from taptr.api.regions import sample_region_queries as sample_region_queries

HOMOGRAPHY_MIN_POINTS = 8
"""Fewer visible points than this fit a similarity (rotation, scale, shift) instead."""

SIMILARITY_MIN_POINTS = 3
"""Fewer visible points than this give no fit: the overlay is hidden on that frame."""


class RegionFit(NamedTuple):
    """A robust fit of the region's motion between two frames.

    Attributes:
        matrix: (3, 3) float64 homography mapping (x, y, 1) pixels of the query frame to
            pixels of the target frame (a similarity when few points were visible).
        inliers: (N,) bool, True for the points that agree with the fit within the RANSAC
            threshold.
    """

    matrix: np.ndarray
    inliers: np.ndarray


@dataclass(frozen=True)
class RegionOverlay:
    """An overlay laid out on the query frame, ready to follow the region.

    Attributes:
        patch: (h, w, 4) float32 RGBA in [0, 1]: the overlay resized to cover the region's
            bounding box on the query frame.
        corner: (x, y) pixel of the query frame where the patch's top-left pixel lies.
        region: (H, W) float32, 1 inside the region on the query frame.
        cells: (H, W) int32 index of the query point nearest to each pixel.
        points: (N, 2) float32 (x, y) query positions in pixels.
    """

    patch: np.ndarray
    corner: tuple[int, int]
    region: np.ndarray
    cells: np.ndarray
    points: np.ndarray


def fit_region_transform(
    source: np.ndarray, target: np.ndarray, *, ransac_threshold: float = 3.0
) -> RegionFit | None:
    """Fits the region's motion from point correspondences, dropping outliers by RANSAC.

    A homography needs `HOMOGRAPHY_MIN_POINTS`; with fewer points, or when the homography
    is implausible (it folds the region over or sends part of it to infinity), a
    similarity (rotation, uniform scale, shift) is fitted instead.

    Args:
        source: (N, 2) (x, y) pixels on the query frame.
        target: (N, 2) (x, y) pixels of the same points on the target frame.
        ransac_threshold: largest reprojection error of an inlier, in pixels.

    Returns:
        The fit, or None with fewer than `SIMILARITY_MIN_POINTS` points or no fit found.
    """
    # OpenCV reads contiguous (N, 2) float32 buffers only.
    source = np.ascontiguousarray(source, dtype=np.float32).reshape(-1, 2)
    target = np.ascontiguousarray(target, dtype=np.float32).reshape(-1, 2)
    if len(source) < SIMILARITY_MIN_POINTS:
        return None
    if len(source) >= HOMOGRAPHY_MIN_POINTS:
        matrix, inliers = cv2.findHomography(source, target, cv2.RANSAC, ransac_threshold)
        if matrix is not None and _is_plausible(matrix, source):
            return RegionFit(matrix, inliers.ravel().astype(bool))
    affine, inliers = cv2.estimateAffinePartial2D(
        source, target, method=cv2.RANSAC, ransacReprojThreshold=ransac_threshold
    )
    if affine is None:
        return None
    return RegionFit(np.vstack([affine, [0.0, 0.0, 1.0]]), inliers.ravel().astype(bool))


def prepare_overlay(overlay: np.ndarray, mask: np.ndarray, points: np.ndarray) -> RegionOverlay:
    """Lays an overlay image out over a region of the query frame.

    The overlay keeps its aspect ratio and is scaled to cover the region's bounding box,
    centred, with whatever sticks out cropped away; it shows only inside the region.

    Args:
        overlay: (h, w, 3) RGB or (h, w, 4) RGBA uint8 image; alpha 0 is transparent.
        mask: (H, W) bool region on the query frame.
        points: (N, 2) (x, y) pixels of the tracked points on the query frame.

    Returns:
        The overlay, region and point cells, for `apply_overlay`.
    """
    mask = np.asarray(mask, dtype=bool)
    points = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 2)
    if overlay.dtype != np.uint8 or overlay.ndim != 3 or overlay.shape[2] not in (3, 4):
        raise ValueError(f"overlay must be (h, w, 3|4) uint8, got {overlay.shape} {overlay.dtype}")
    if mask.ndim != 2 or not mask.any() or len(points) == 0:
        raise ValueError("need a non-empty (H, W) region mask and at least one point")
    if overlay.shape[2] == 3:
        overlay = np.dstack([overlay, np.full(overlay.shape[:2], 255, np.uint8)])
    x, y, box_w, box_h = cv2.boundingRect(mask.astype(np.uint8))
    scale = max(box_w / overlay.shape[1], box_h / overlay.shape[0])
    size = (
        max(box_w, round(overlay.shape[1] * scale)),
        max(box_h, round(overlay.shape[0] * scale)),
    )
    shrinking = scale < 1  # area averaging avoids aliasing when shrinking
    resized = cv2.resize(
        overlay, size, interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR
    )
    left, top = (size[0] - box_w) // 2, (size[1] - box_h) // 2
    patch = resized[top : top + box_h, left : left + box_w].astype(np.float32) / 255
    return RegionOverlay(
        patch=patch,
        corner=(x, y),
        region=mask.astype(np.float32),
        cells=_nearest_point_cells(points, mask.shape),
        points=points,
    )


def apply_overlay(
    frame: np.ndarray,
    overlay: RegionOverlay,
    positions: np.ndarray,
    visible: np.ndarray,
    *,
    opacity: float = 1.0,
    min_visible_fraction: float = 0.5,
    ransac_threshold: float = 3.0,
) -> tuple[np.ndarray, RegionFit | None]:
    """Blends the overlay onto the region in one frame.

    Args:
        frame: (H, W, 3) uint8 RGB frame.
        overlay: from `prepare_overlay`, on a frame of the same size.
        positions: (N, 2) (x, y) pixels of the tracked points on this frame.
        visible: (N,) bool, True where a point is visible on this frame.
        opacity: overlay opacity in [0, 1], multiplied with the overlay's alpha.
        min_visible_fraction: hide the overlay when fewer points than this are visible.
        ransac_threshold: largest reprojection error of an inlier, in pixels.

    Returns:
        The (H, W, 3) uint8 RGB edited frame (a copy), and the fit (None where hidden).
    """
    visible = np.asarray(visible, dtype=bool)
    if frame.shape[:2] != overlay.region.shape or visible.shape != (len(overlay.points),):
        raise ValueError("frame, overlay region and points do not match")
    if visible.sum() < max(SIMILARITY_MIN_POINTS, min_visible_fraction * len(visible)):
        return frame.copy(), None
    fit = fit_region_transform(
        overlay.points[visible], np.asarray(positions)[visible], ransac_threshold=ransac_threshold
    )
    if fit is None:
        return frame.copy(), None
    height, width = frame.shape[:2]
    # The region, minus the cells of occluded points, goes through the same warp.
    region = overlay.region * visible[overlay.cells]
    region = cv2.warpPerspective(region, fit.matrix, (width, height), flags=cv2.INTER_LINEAR)
    place = np.array([[1, 0, overlay.corner[0]], [0, 1, overlay.corner[1]], [0, 0, 1]], float)
    patch = cv2.warpPerspective(
        overlay.patch, fit.matrix @ place, (width, height), flags=cv2.INTER_LINEAR
    )
    alpha = (opacity * patch[..., 3] * region)[..., None]
    blended = frame.astype(np.float32) * (1 - alpha) + patch[..., :3] * 255 * alpha
    return np.clip(np.round(blended), 0, 255).astype(np.uint8), fit


def overlay_region(
    video: np.ndarray,
    overlay: np.ndarray,
    mask: np.ndarray,
    tracks: np.ndarray,
    visibility: np.ndarray,
    query_frame: int,
    *,
    opacity: float = 1.0,
    min_visible_fraction: float = 0.5,
    ransac_threshold: float = 3.0,
) -> np.ndarray:
    """Pastes an overlay onto a tracked region in every frame of a video.

    Args:
        video: (T, H, W, 3) uint8 RGB frames.
        overlay: (h, w, 3) RGB or (h, w, 4) RGBA uint8 image.
        mask: (H, W) bool region on the query frame.
        tracks: (T, N, 2) (x, y) pixels of points tracked from the query frame, for example
            from `sample_region_queries`.
        visibility: (T, N) bool, True where a point is visible.
        query_frame: frame index the mask and the points' queries belong to.
        opacity: overlay opacity in [0, 1], multiplied with the overlay's alpha.
        min_visible_fraction: hide the overlay on frames where fewer points are visible.
        ransac_threshold: largest reprojection error of an inlier, in pixels.

    Returns:
        (T, H, W, 3) uint8 RGB edited frames.
    """
    if tracks.shape[:1] != video.shape[:1] or visibility.shape != tracks.shape[:2]:
        raise ValueError(
            f"video {video.shape}, tracks {tracks.shape} and visibility {visibility.shape} "
            "must have the same T (and N)"
        )
    prepared = prepare_overlay(overlay, mask, tracks[query_frame])
    edited = [
        apply_overlay(
            frame,
            prepared,
            tracks[t],
            visibility[t],
            opacity=opacity,
            min_visible_fraction=min_visible_fraction,
            ransac_threshold=ransac_threshold,
        )[0]
        for t, frame in enumerate(video)
    ]
    return np.stack(edited)


def _is_plausible(matrix: np.ndarray, points: np.ndarray) -> bool:
    """Whether a homography keeps the orientation and every point in front of the camera."""
    matrix = matrix / matrix[2, 2] if matrix[2, 2] != 0 else matrix
    depth = points @ matrix[2, :2] + matrix[2, 2]
    return bool(np.linalg.det(matrix) > 0 and (depth > 0).all())


def _nearest_point_cells(points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W) int32 index of the point nearest to each pixel (Voronoi cells of the points)."""
    height, width = size
    cols = np.clip(np.round(points[:, 0]), 0, width - 1).astype(np.int64)
    rows = np.clip(np.round(points[:, 1]), 0, height - 1).astype(np.int64)
    seeds = np.full(size, 255, np.uint8)
    seeds[rows, cols] = 0  # the distance transform measures the distance to zero pixels
    _, labels = cv2.distanceTransformWithLabels(
        seeds, cv2.DIST_L2, cv2.DIST_MASK_PRECISE, labelType=cv2.DIST_LABEL_PIXEL
    )
    # Each seed pixel gets its own label; map labels back to point indices (points sharing a
    # pixel share its cell).
    to_point = np.zeros(labels.max() + 1, np.int32)
    to_point[labels[rows, cols]] = np.arange(len(points), dtype=np.int32)
    return to_point[labels]
