"""Bucketed FAST detection: spread over the image, and topping up features already held."""

import numpy as np

from services.egomotion.features import FeatureParams, bucket_of, detect_bucketed
from services.egomotion.scene import BoxRoom, pinhole

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
