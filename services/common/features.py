"""Feature detection with bucketing and pyramidal Lucas–Kanade tracking, shared by the stereo
and mono estimators and the loop closure's geometry.

Bucketing follows LIBVISO2 (Geiger, Ziegler & Stiller, "StereoScan: Dense 3d reconstruction
in real-time", IV 2011, Sec. III-A): the image is divided into square buckets and only the
strongest few features of each are kept, so that features spread over the image and the
pose is not dominated by one textured corner.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class FeatureParams:
    fast_threshold: int = 20
    bucket_size_px: int = 50
    features_per_bucket: int = 4
    border_px: int = 12  # no features where the tracking window would leave the image
    min_distance_px: int = 3  # no new corner within this square half-width of a held feature


def detect_bucketed(
    image: np.ndarray, params: FeatureParams, mask: np.ndarray | None = None, held: np.ndarray | None = None
) -> np.ndarray:
    """FAST corners, strongest ``features_per_bucket`` per bucket, as an (N, 2) float32 array.

    ``held`` (M, 2) are features the caller already has (e.g. tracked from the last frame):
    each bucket is then only topped up to ``features_per_bucket``, with corners at least
    ``params.min_distance_px`` from every held feature (not the same corner again).

    If the image yields few corners at the configured threshold, the threshold is lowered once
    (to a quarter) so that low-contrast images still give something to track.
    """
    size, height, width = params.bucket_size_px, image.shape[0], image.shape[1]
    columns = width // size + 1
    buckets_total = (height // size + 1) * columns
    room = np.full(buckets_total, params.features_per_bucket, np.int64)
    if held is not None and len(held):
        room -= np.bincount(bucket_of(held, size, columns), minlength=buckets_total)
        mask = _free(mask, held, room.reshape(-1, columns) > 0, size, params.min_distance_px, image.shape[:2])
    points, responses = _fast(image, params.fast_threshold, params.border_px, mask)
    if len(points) + (0 if held is None else len(held)) < buckets_total and params.fast_threshold > 4:
        points, responses = _fast(image, max(2, params.fast_threshold // 4), params.border_px, mask)
    if len(points) == 0:
        return np.empty((0, 2), np.float32)
    keep = first_per_bucket(bucket_of(points, size, columns), room, -responses)  # strongest first
    return points[keep].astype(np.float32)


def bucket_of(points: np.ndarray, size: int, columns: int) -> np.ndarray:
    """The bucket index (row-major, ``columns`` buckets a row) of each (x, y) point."""
    return (points[:, 1] // size).astype(np.int64) * columns + (points[:, 0] // size).astype(np.int64)


def first_per_bucket(bucket: np.ndarray, limit: int | np.ndarray, rank_by: np.ndarray | None = None) -> np.ndarray:
    """Indices of the first ``limit`` entries (a number, or one per bucket index) of each
    bucket, ordered by ``rank_by`` ascending within a bucket (default: as given)."""
    order = np.lexsort((np.arange(len(bucket)) if rank_by is None else rank_by, bucket))
    bucket_sorted = bucket[order]
    rank = np.arange(len(order)) - np.searchsorted(bucket_sorted, bucket_sorted, side="left")
    limits = limit[bucket_sorted] if isinstance(limit, np.ndarray) else limit
    return order[rank < limits]


def _free(
    mask: np.ndarray | None, held: np.ndarray, open_buckets: np.ndarray, size: int, distance: int, shape: tuple[int, int]
) -> np.ndarray:
    """A detection mask: nonzero in buckets with room, away from the held features."""
    rows, columns = open_buckets.shape
    free = cv2.resize(open_buckets.astype(np.uint8) * 255, (columns * size, rows * size), interpolation=cv2.INTER_NEAREST)
    free = np.ascontiguousarray(free[: shape[0], : shape[1]])
    near = np.zeros(shape, np.uint8)
    xy = np.round(held).astype(np.int64)
    inside = (xy[:, 0] >= 0) & (xy[:, 0] < shape[1]) & (xy[:, 1] >= 0) & (xy[:, 1] < shape[0])
    near[xy[inside, 1], xy[inside, 0]] = 255
    if distance > 0:
        near = cv2.dilate(near, np.ones((2 * distance + 1, 2 * distance + 1), np.uint8))
    free = cv2.subtract(free, near)
    return free if mask is None else cv2.bitwise_and(free, mask)


def _fast(image: np.ndarray, threshold: int, border: int, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    detector = cv2.FastFeatureDetector_create(threshold=int(threshold), nonmaxSuppression=True)
    keypoints = detector.detect(image, mask)
    if not keypoints:
        return np.empty((0, 2)), np.empty(0)
    points = cv2.KeyPoint_convert(keypoints).astype(np.float64)
    responses = np.array([k.response for k in keypoints], dtype=np.float64)
    height, width = image.shape[:2]
    inside = (
        (points[:, 0] >= border)
        & (points[:, 0] < width - border)
        & (points[:, 1] >= border)
        & (points[:, 1] < height - border)
    )
    return points[inside], responses[inside]


@dataclass(frozen=True)
class TrackParams:
    window_px: int = 21
    pyramid_levels: int = 3
    # A track is kept only if tracking it back lands this close; 0 skips the backward pass
    # (half the cost; for stereo matching, where the epipolar row check rejects bad matches).
    forward_backward_px: float = 1.0
    # Refine each track allowing the window's brightness to change by a gain and an offset
    # (refine_affine_brightness); plain Lucas–Kanade assumes it constant.
    affine_brightness: bool = False


def track(
    previous: np.ndarray,
    current: np.ndarray,
    points: np.ndarray,
    params: TrackParams,
    guess: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Track ``points`` (N, 2) from ``previous`` into ``current`` with pyramidal Lucas–Kanade
    and a forward–backward check (Kalal et al., "Forward-backward error", ICPR 2010).

    ``guess`` (N, 2) is an initial position in ``current`` (e.g. predicted from the last
    motion). Returns the tracked positions (N, 2) and a boolean mask of good tracks.
    """
    if len(points) == 0:
        return np.empty((0, 2), np.float32), np.zeros(0, bool)
    points = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    window = (params.window_px, params.window_px)
    flags = 0
    start = None
    if guess is not None:
        start = np.ascontiguousarray(guess, dtype=np.float32).reshape(-1, 1, 2).copy()
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    tracked, status, _ = cv2.calcOpticalFlowPyrLK(
        previous, current, points, start, winSize=window, maxLevel=params.pyramid_levels, criteria=criteria, flags=flags
    )
    good = status.ravel() == 1
    if params.forward_backward_px > 0:
        back, status_back, _ = cv2.calcOpticalFlowPyrLK(
            current,
            previous,
            tracked,
            points.copy(),
            winSize=window,
            maxLevel=params.pyramid_levels,
            criteria=criteria,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        fb_error = np.linalg.norm(back.reshape(-1, 2) - points.reshape(-1, 2), axis=1)
        good &= (status_back.ravel() == 1) & (fb_error < params.forward_backward_px)
    tracked = tracked.reshape(-1, 2)
    if params.affine_brightness and good.any():
        refined, converged = refine_affine_brightness(previous, current, points.reshape(-1, 2)[good], tracked[good], params.window_px)
        tracked[good] = refined
        good[good] = converged
    height, width = current.shape[:2]
    good = (
        good
        & (tracked[:, 0] >= 0)
        & (tracked[:, 0] <= width - 1)
        & (tracked[:, 1] >= 0)
        & (tracked[:, 1] <= height - 1)
    )
    return tracked, good


def refine_affine_brightness(
    previous: np.ndarray, current: np.ndarray, points: np.ndarray, tracked: np.ndarray, window_px: int,
    iterations: int = 4, max_move_px: float = 1.0, converged_px: float = 0.005,
) -> tuple[np.ndarray, np.ndarray]:
    """Refine ``tracked`` (N, 2), the positions in ``current`` of ``points`` in ``previous``,
    letting the brightness of each window change by a gain and an offset.

    Lucas–Kanade assumes a patch keeps its brightness. Under a lens vignette it does not: a
    patch moving outwards darkens, and the constant-brightness fit pulls it back towards the
    brighter side, so that the flow of forward motion comes out short (0.5 % on the synthetic
    world, and the path with it); a change of exposure between frames does the same. Here each
    window is fitted as current(x + d) = a·previous(x) + b from the Lucas–Kanade result, the
    brightness model of direct methods (Engel, Koltun & Cremers, "Direct sparse odometry", TPAMI
    2018, eq. 4).
    Returns the refined positions and a mask of those that converged (the last step below
    10 × ``converged_px``; the iterations stop early once every step is below ``converged_px``)
    within ``max_move_px`` of where they started; the others keep their start.
    """
    half = window_px // 2
    offsets = np.arange(-half, half + 1, dtype=np.float32)
    offset_x, offset_y = (grid.ravel() for grid in np.meshgrid(offsets, offsets))
    # The template is sampled one pixel wider, so central differences give its gradients.
    wide = np.arange(-half - 1, half + 2, dtype=np.float32)
    wide_x, wide_y = (grid.ravel() for grid in np.meshgrid(wide, wide))
    count, side = len(points), len(wide)
    patch = _sample(previous.astype(np.float32), points, wide_x, wide_y).reshape(count, side, side)
    template = patch[:, 1:-1, 1:-1].reshape(count, -1)
    # Inverse compositional with the gain and offset projected out (Baker & Matthews, "Lucas-Kanade
    # 20 years on", part 3, IJCV 2004): the template's gradients are made orthogonal to the
    # template and to a constant, so the best gain and offset drop out of every step, and the
    # Hessian is computed once.
    centred = template - template.mean(axis=1, keepdims=True)
    unit = centred / np.maximum(np.linalg.norm(centred, axis=1, keepdims=True), 1e-6)
    steepest = []
    for gradient in (patch[:, 1:-1, 2:] - patch[:, 1:-1, :-2], patch[:, 2:, 1:-1] - patch[:, :-2, 1:-1]):
        gradient = 0.5 * gradient.reshape(count, -1)
        gradient -= gradient.mean(axis=1, keepdims=True)
        steepest.append(gradient - unit * np.einsum("ij,ij->i", unit, gradient)[:, None])
    sx, sy = steepest
    hxx, hxy, hyy = np.einsum("ij,ij->i", sx, sx), np.einsum("ij,ij->i", sx, sy), np.einsum("ij,ij->i", sy, sy)
    det = hxx * hyy - hxy * hxy
    ok = det > 1e-6 * (hxx + hyy) ** 2
    det = np.where(ok, det, 1.0)
    current = current.astype(np.float32)
    start = np.asarray(tracked, np.float32)
    position = start.copy()
    for _ in range(iterations):
        values = _sample(current, position, offset_x, offset_y)
        bx, by = np.einsum("ij,ij->i", sx, values), np.einsum("ij,ij->i", sy, values)
        step = np.column_stack(((hyy * bx - hxy * by) / det, (hxx * by - hxy * bx) / det))
        step = np.where(ok[:, None], np.clip(step, -max_move_px, max_move_px), 0.0)
        position -= step.astype(np.float32)
        last = np.abs(step).max(axis=1)
        if last.max(initial=0.0) < converged_px:
            break
    converged = ok & (last < 10 * converged_px) & (np.abs(position - start).max(axis=1) <= max_move_px)
    return np.where(converged[:, None], position, start), converged


def _sample(image: np.ndarray, centres: np.ndarray, offset_x: np.ndarray, offset_y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` at ``centres`` (N, 2) + the offsets: an (N, len(offsets)) array."""
    map_x = (centres[:, :1] + offset_x[None, :]).astype(np.float32)
    map_y = (centres[:, 1:2] + offset_y[None, :]).astype(np.float32)
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def global_shift(previous: np.ndarray, current: np.ndarray, downscale: int = 4) -> tuple[float, float]:
    """The dominant image translation from ``previous`` to ``current`` in pixels, by phase
    correlation (Kuglin & Hines 1975) of downscaled, Hann-windowed images. A cheap seed for
    tracking through a sudden turn, where the whole image slides by hundreds of pixels."""
    small = [
        cv2.resize(image, None, fx=1.0 / downscale, fy=1.0 / downscale, interpolation=cv2.INTER_AREA).astype(np.float32)
        for image in (previous, current)
    ]
    window = cv2.createHanningWindow(small[0].shape[::-1], cv2.CV_32F)
    (dx, dy), _ = cv2.phaseCorrelate(small[0], small[1], window)
    return dx * downscale, dy * downscale
