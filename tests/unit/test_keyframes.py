"""Keyframes as bytes (services/loopclosure/geometry.py) and the keyframe store on disk
(services/loopclosure/keyframes.py)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from services.common.journal import JournalError
from services.loopclosure.geometry import DISPARITY_STEP, ClosureGeometry, Keyframe, KeyframeError
from services.loopclosure.keyframes import KeyframeStore
from services.common.frames import Camera
from services.source.synthetic import SyntheticWorld, WorldConfig

CAMERA = Camera(400.0, 400.0, 319.5, 239.5, 0.12, 640, 480)


def random_keyframe(seed: int, count: int = 50, stereo: bool = True) -> Keyframe:
    """A keyframe of random features (as stored: quantised), NaN disparity for a few."""
    rng = np.random.default_rng(seed)
    keypoints = rng.uniform([0, 0], [639, 479], (count, 2)).astype(np.float32)
    descriptors = rng.integers(0, 256, (count, 32), dtype=np.uint8)
    disparity = None
    if stereo:
        disparity = rng.uniform(0.6, 120.0, count).astype(np.float32)
        disparity[::7] = np.nan
    return Keyframe.from_bytes(Keyframe(keypoints, descriptors, disparity, CAMERA if stereo else None, (640, 480)).to_bytes())


def same(a: Keyframe, b: Keyframe) -> bool:
    disparities = (a.disparity is None and b.disparity is None) or (
        a.disparity is not None and b.disparity is not None and np.array_equal(a.disparity, b.disparity, equal_nan=True))
    return a.to_bytes() == b.to_bytes() and np.array_equal(a.keypoints, b.keypoints) and \
        np.array_equal(a.descriptors, b.descriptors) and disparities and a.camera == b.camera


# --- keyframes as bytes ------------------------------------------------------------------------

def test_bytes_round_trip_loses_nothing_that_matters():
    rng = np.random.default_rng(1)
    keypoints = rng.uniform([0, 0], [639, 479], (200, 2)).astype(np.float32)
    descriptors = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    # From 1000 px (a point 5 cm away) to 0.05 px (1 km away at f·b = 48 px·m).
    disparity = np.geomspace(0.05, 1000.0, 200).astype(np.float32)
    disparity[5] = np.nan
    original = Keyframe(keypoints, descriptors, disparity, CAMERA, (640, 480))
    back = Keyframe.from_bytes(original.to_bytes())
    assert np.array_equal(back.descriptors, descriptors) and back.camera == CAMERA and back.image_size == (640, 480)
    assert np.abs(back.keypoints - keypoints).max() <= 1 / 128 + 1e-6      # 1/64 px steps at 640×480
    assert np.isnan(back.disparity[5]) and np.isnan(back.points[5]).all()
    finite = np.isfinite(disparity)
    # Disparities round to 1/64 px: far below the ~0.1 px of stereo matching, at every depth
    # (a relative depth error of at most (1/128)/d, i.e. the depth a 1/128 px disparity error gives).
    assert np.abs(back.disparity[finite] - disparity[finite]).max() <= DISPARITY_STEP / 2 + 1e-6
    near = finite & (disparity >= 1.0)
    depth_error = np.abs(back.points[near, 2] / original.points[near, 2] - 1)
    assert np.all(depth_error <= DISPARITY_STEP / 2 / disparity[near] + 1e-6)
    assert same(Keyframe.from_bytes(back.to_bytes()), back)      # stored values survive unchanged


def test_a_keyframe_takes_under_8_kb():
    world = SyntheticWorld(WorldConfig(seed=0))
    frame = world[20]
    keyframe = ClosureGeometry().keyframe(frame.left, frame.right, frame.camera)
    size = len(keyframe.to_bytes())
    assert len(keyframe) == 200 and keyframe.depth_count == 200
    assert size == 10 + 40 + 200 * (4 + 32 + 2) and size <= 8 * 1024
    mono = ClosureGeometry().keyframe(frame.left, None, frame.camera)
    assert mono.points is None and len(mono.to_bytes()) == 10 + 40 + 200 * (4 + 32)


def test_points_follow_the_camera_convention():
    keyframe = random_keyframe(2)
    u, v = keyframe.keypoints[:, 0], keyframe.keypoints[:, 1]
    z = CAMERA.fx * CAMERA.baseline / keyframe.disparity
    expected = np.column_stack(((u - CAMERA.cx) * z / CAMERA.fx, (v - CAMERA.cy) * z / CAMERA.fy, z))
    np.testing.assert_allclose(keyframe.points, expected, rtol=1e-6)
    assert random_keyframe(2, stereo=False).points is None


def test_bad_bytes_are_refused():
    data = random_keyframe(3).to_bytes()
    with pytest.raises(KeyframeError, match="unknown version 9"):
        Keyframe.from_bytes(b"\x09" + data[1:])
    with pytest.raises(KeyframeError, match="header announces"):
        Keyframe.from_bytes(data[:-1])
    with pytest.raises(KeyframeError, match="shorter than its header"):
        Keyframe.from_bytes(data[:4])


def test_wide_images_keep_coarser_keypoints():
    keypoints = np.array([[4095.93, 10.02], [0.0, 2999.5]], np.float32)
    keyframe = Keyframe(keypoints, np.zeros((2, 32), np.uint8), None, None, (4096, 3000))
    back = Keyframe.from_bytes(keyframe.to_bytes())
    assert np.abs(back.keypoints - keypoints).max() <= 1 / 16 + 1e-4        # 1/8 px steps at 4096 px
    assert np.abs(back.keypoints - keypoints).max() > 1 / 128                # coarser than at 640 px


# --- the store ---------------------------------------------------------------------------------

def test_store_round_trip_and_reopen(tmp_path):
    path = tmp_path / "keyframes.bin"
    frames = {i: random_keyframe(i, stereo=i % 2 == 0) for i in range(5)}
    with KeyframeStore(path) as store:
        for i, keyframe in frames.items():
            assert store.append(i, keyframe)
        assert len(store) == 5 and 3 in store and 5 not in store and -1 not in store
        assert all(same(store.get(i), keyframe) for i, keyframe in frames.items())
        assert store.get(7) is None
    with KeyframeStore(path) as store:
        assert len(store) == 5 and all(same(store.get(i), keyframe) for i, keyframe in frames.items())
        assert store.append(5, random_keyframe(5))
    with KeyframeStore(path) as store:
        assert len(store) == 6 and same(store.get(5), random_keyframe(5))
        assert store.size == path.stat().st_size


def test_appending_again_replaces(tmp_path):
    path = tmp_path / "keyframes.bin"
    with KeyframeStore(path) as store:
        store.append(0, random_keyframe(0))
        first = store.get(0)
        store.append(0, random_keyframe(9))
        assert len(store) == 1 and same(store.get(0), random_keyframe(9)) and store.get(0) is not first
    with KeyframeStore(path) as store:
        assert len(store) == 1 and same(store.get(0), random_keyframe(9))


def test_torn_last_record_is_cut_off(tmp_path, caplog):
    path = tmp_path / "keyframes.bin"
    with KeyframeStore(path) as store:
        for i in range(3):
            store.append(i, random_keyframe(i))
        end_of_second = store.size - len(random_keyframe(2).to_bytes()) - 16
    for cut in (10, len(random_keyframe(2).to_bytes()) + 10):      # inside the payload, inside the header
        data = path.read_bytes()
        path.write_bytes(data[:end_of_second + 16 + len(random_keyframe(2).to_bytes()) - cut])
        with caplog.at_level(logging.WARNING, logger="services.loopclosure.keyframes"):
            with KeyframeStore(path) as store:
                assert len(store) == 2 and 2 not in store and same(store.get(1), random_keyframe(1))
                assert path.stat().st_size == end_of_second
                store.append(2, random_keyframe(2))                  # appends follow intact records
        assert "torn last record" in caplog.text
        caplog.clear()
    with KeyframeStore(path) as store:
        assert len(store) == 3 and same(store.get(2), random_keyframe(2))


def test_last_record_with_a_bad_checksum_is_torn(tmp_path, caplog):
    path = tmp_path / "keyframes.bin"
    with KeyframeStore(path) as store:
        store.append(0, random_keyframe(0))
        store.append(1, random_keyframe(1))
    data = bytearray(path.read_bytes())
    data[-5] ^= 0xFF
    path.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING):
        with KeyframeStore(path) as store:
            assert len(store) == 1
    assert "torn last record" in caplog.text


def test_damaged_record_in_the_middle_is_an_error(tmp_path):
    path = tmp_path / "keyframes.bin"
    with KeyframeStore(path) as store:
        for i in range(3):
            store.append(i, random_keyframe(i))
    record = 16 + len(random_keyframe(0).to_bytes())       # record 1's byte offset (after the file header)
    data = bytearray(path.read_bytes())
    data[record + 16 + 40] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(JournalError, match=f"keyframes.bin: byte {16 + len(random_keyframe(0).to_bytes()) + 16}: "
                                           "keyframe record is damaged"):
        KeyframeStore(path)
    assert path.read_bytes() == bytes(data)                 # left as it was


def test_damage_after_opening_is_found_when_read(tmp_path):
    path = tmp_path / "keyframes.bin"
    store = KeyframeStore(path, cache=0)
    store.append(0, random_keyframe(0))
    store.append(1, random_keyframe(1))
    with open(path, "r+b") as handle:
        handle.seek(16 + 16 + 100)
        handle.write(b"\x00\x00\x00")
    with pytest.raises(JournalError, match="byte 16: keyframe record of template 0 is damaged"):
        store.get(0)
    assert same(store.get(1), random_keyframe(1))
    store.close()


def test_a_foreign_file_is_refused_untouched(tmp_path):
    path = tmp_path / "not_keyframes.bin"
    path.write_bytes(b"frame,x,y\n0,1,2\n")
    with pytest.raises(JournalError, match="not a keyframe store"):
        KeyframeStore(path)
    assert path.read_bytes() == b"frame,x,y\n0,1,2\n"
    other = tmp_path / "other_version.bin"
    other.write_bytes(b"GSKFSTOR" + (7).to_bytes(4, "little") + bytes(4))
    with pytest.raises(JournalError, match="version 7"):
        KeyframeStore(other)
    short = tmp_path / "short.bin"
    short.write_bytes(b"ab")
    with pytest.raises(JournalError, match="not a keyframe store"):
        KeyframeStore(short)


def test_a_torn_header_is_written_again(tmp_path):
    path = tmp_path / "keyframes.bin"
    path.write_bytes(b"GSKF")                               # the process died writing the header
    with KeyframeStore(path) as store:
        assert len(store) == 0 and store.append(0, random_keyframe(0))
    with KeyframeStore(path) as store:
        assert same(store.get(0), random_keyframe(0))


def test_the_file_is_bounded(tmp_path, caplog):
    path = tmp_path / "keyframes.bin"
    record = 16 + len(random_keyframe(0).to_bytes())
    with caplog.at_level(logging.WARNING):
        with KeyframeStore(path, max_bytes=16 + 2 * record) as store:
            assert store.append(0, random_keyframe(0)) and store.append(1, random_keyframe(1))
            assert not store.append(2, random_keyframe(2)) and not store.append(3, random_keyframe(3))
            assert store.dropped == 2 and len(store) == 2 and store.get(2) is None
            assert path.stat().st_size == 16 + 2 * record
    assert caplog.text.count("full") == 1                   # logged once


def test_truncate_drops_later_templates(tmp_path):
    path = tmp_path / "keyframes.bin"
    with KeyframeStore(path) as store:
        for i in range(5):
            store.append(i, random_keyframe(i))
        size_of_three = 16 + sum(16 + len(random_keyframe(i).to_bytes()) for i in range(3))
        assert store.truncate(3) == 2 and store.truncate(3) == 0
        assert len(store) == 3 and 3 not in store and store.get(4) is None
        assert path.stat().st_size == size_of_three == store.size
        store.append(3, random_keyframe(13))
    with KeyframeStore(path) as store:
        assert len(store) == 4 and same(store.get(3), random_keyframe(13))


def test_truncate_keeps_a_replacement_written_after_a_dropped_record(tmp_path):
    path = tmp_path / "keyframes.bin"
    with KeyframeStore(path) as store:
        for i in range(3):
            store.append(i, random_keyframe(i))
        store.append(1, random_keyframe(11))                # template 1 again, after template 2
        assert store.truncate(2) == 1
        assert len(store) == 2 and same(store.get(1), random_keyframe(11)) and 2 not in store
    with KeyframeStore(path) as store:
        assert len(store) == 2 and same(store.get(0), random_keyframe(0)) and same(store.get(1), random_keyframe(11))
    assert not (tmp_path / "keyframes.bin.tmp").exists()


def test_the_cache_keeps_the_most_recently_used(tmp_path):
    with KeyframeStore(tmp_path / "keyframes.bin", cache=2) as store:
        for i in range(3):
            store.append(i, random_keyframe(i))
        a = store.get(0)
        b = store.get(1)
        assert store.get(0) is a                            # cached: the same object
        store.get(2)                                        # evicts 1, the least recently used
        assert store.get(0) is a and store.get(1) is not b and same(store.get(1), b)
