"""Bucketed FAST detection: spread over the image, and topping up features already held; tracking
through a change of brightness that is not constant over a window."""

import cv2
import numpy as np
import pytest

from services.common.features import FeatureParams, TrackParams, bucket_of, detect_bucketed, track
from services.benchmarks.box_room import BoxRoom, pinhole

PARAMS = FeatureParams(fast_threshold=20, bucket_size_px=32, features_per_bucket=4, min_distance_px=3)


def image():
    return BoxRoom(seed=3).render(pinhole(320, 240), np.eye(4))


def counts(points, size=32, width=320, height=240):
    columns = width // size + 1
    return np.bincount(bucket_of(points, size, columns), minlength=(height // size + 1) * columns)


def test_at_most_features_per_bucket_and_spread():
    points = detect_bucketed(image(), PARAMS)
    per_bucket = counts(points)
    assert per_bucket.max() == PARAMS.features_per_bucket
    assert (per_bucket > 0).sum() >= 50  # of 80 buckets, the textured room fills most


def test_held_features_are_topped_up_not_repeated():
    picture = image()
    alone = detect_bucketed(picture, PARAMS)
    # Hold every second corner, off by a pixel (as if tracked from the last frame), plus a full
    # bucket's worth in bucket 0.
    held = np.concatenate((alone[::2] + np.float32([1.4, -0.6]), np.float32([[13, 13], [15, 20], [20, 15], [25, 25]])))
    new = detect_bucketed(picture, PARAMS, held=held)
    assert len(new) > 0
    total = counts(np.concatenate((held, new)))
    held_only = counts(held)
    # Buckets are filled up to features_per_bucket, never beyond what was held already.
    assert (total <= np.maximum(held_only, PARAMS.features_per_bucket)).all()
    assert counts(new)[0] == 0
    # No new corner repeats a held one (min_distance_px away from each).
    distance = np.abs(new[:, None, :] - held[None, :, :]).max(axis=2).min(axis=1)
    assert distance.min() > PARAMS.min_distance_px
    # The other half of the original corners come back where their buckets have room.
    assert len(new) >= len(alone[1::2]) // 2


def vignetted(picture: np.ndarray, shift: tuple[float, float] = (0.0, 0.0), gain: float = 1.0) -> np.ndarray:
    """`picture` moved by `shift` pixels, times `gain`, seen through a lens vignette (brightness
    falling off towards the edges, as in the synthetic world): a patch that moves changes its
    brightness, and not by the same factor across a window."""
    height, width = picture.shape
    moved = cv2.warpAffine(picture.astype(np.float32), np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), (width, height),
                           flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    x, y = np.meshgrid((np.arange(width) - width / 2) / 190.0, (np.arange(height) - height / 2) / 190.0)
    return np.clip(gain * moved / (1 + 0.25 * (x**2 + y**2)) ** 2 + 0.5, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("gain", [0.95, 1.0, 1.05])
def test_affine_brightness_refinement_tracks_through_a_change_of_exposure(gain):
    """Under a vignette, a 5 % change of exposure nearly doubles plain Lucas–Kanade's error; the
    refined tracks keep the error of an unchanged exposure, and lose nothing without a change."""
    picture = image()
    shift = (1.3, -0.7)
    previous, current = vignetted(picture), vignetted(picture, shift, gain)
    points = detect_bucketed(previous, PARAMS)
    points = points[(np.abs(points - [160, 120]) < [130, 90]).all(axis=1)]
    expected = points + np.float32(shift)
    plain, good = track(previous, current, points, TrackParams(11, 3, 1.0))
    refined, kept = track(previous, current, points, TrackParams(11, 3, 1.0, affine_brightness=True))
    assert good.sum() > 150 and kept.sum() > 0.9 * good.sum()
    plain_error = np.median(np.linalg.norm(plain - expected, axis=1)[good])
    refined_error = np.median(np.linalg.norm(refined - expected, axis=1)[kept])
    if gain == 1.0:
        assert refined_error < 1.15 * plain_error
    else:
        assert plain_error > 0.09 and refined_error < 0.07
