"""A live ROS 2 camera as a frame source (`--source ros2:TOPIC`): `sensor_msgs/Image` or
`CompressedImage` samples heard on Zenoh (rmw_zenoh's keys, or zenoh-bridge-ros2dds'), with
`--camera-info-topic` (sensor_msgs/CameraInfo), `--right-image-topic` (a stereo pair matched by
stamp within `stereo_tolerance`) and `--odom-topic` (nav_msgs/Odometry: its planar pose at each
image's stamp gives the frame's odometry and ground truth, as a bag's does, so the passthrough
estimator runs on a robot's wheel odometry). The images decode as a bag's do (rosbag.py).

No Zenoh here: the source service subscribes on its session (`subscriptions()`, graph.py) and
hands every sample to `on_sample` (a Zenoh thread); iteration hands out the newest frame. A
live source cannot be replayed: a frame replaced before the pipeline took it is dropped and
counted (`frames_dropped`), and `seq` counts every image heard, so drops show as gaps.

Bad input is counted (`counters`), logged once per key and kind, and dropped: a payload that is
not CDR of its type, a type other than the topic's, a sample without rmw_zenoh's attachment,
an image whose data does not match its size and step.
"""

from __future__ import annotations

import collections
import logging
import struct
import threading
import time
from typing import Iterator

import numpy as np

from services.source.calibration import DEFAULT_FOV_DEG, assumed_camera
from services.common.geometry import planar_motion
from services.common.frames import Camera, Frame, SourceError
from services.source.rosbag import (
    CAMERA_INFO_TYPE, IMAGE_TYPES, ODOMETRY_TYPE, camera_from_info, camera_pose_of_planar, decode_image,
    interpolate_planar,
)

log = logging.getLogger(__name__)

IMAGE_TYPE, COMPRESSED_IMAGE_TYPE = IMAGE_TYPES
ODOMETRY_KEPT = 4096     # odometry poses kept to place images in time
PAIRS_WAITING = 16       # left and right images kept while their partner is awaited
WAIT_LOG_S = 10.0
BAD_INPUTS = ("malformed", "unexpected_type", "no_attachment", "bad_image")


def header_stamp_ns(cdr: bytes) -> int:
    """The header stamp of a message whose first field is a std_msgs/Header (after CDR's
    4-byte encapsulation header: int32 sec, uint32 nanosec, little-endian)."""
    sec, nanosec = struct.unpack_from("<iI", cdr, 4)
    return sec * 1_000_000_000 + nanosec


class Ros2Source:
    """Frames from ROS 2 topics (module docstring). `topic` is the image topic, absolute."""

    live = True

    def __init__(self, topic: str, *, right_image_topic: str | None = None, camera_info_topic: str | None = None,
                 odom_topic: str | None = None, stereo_tolerance: float = 0.005, camera: Camera | None = None,
                 grey: bool = False, mono: bool = False, start: int = 0, stop: int | None = None, step: int = 1,
                 fov: float | None = None):
        if start < 0 or (stop is not None and stop <= start) or step < 1:
            raise SourceError(f"ros2:{topic}: invalid frame selection start={start} stop={stop} step={step}")
        from services.ros2wire.messages import typestore

        self.store = typestore()   # (Image, CameraInfo and Odometry read the same in every distribution)
        self.name = f"ros2:{topic}"
        self.topics = {"image": _absolute(topic)}
        if right_image_topic and not mono:
            self.topics["right"] = _absolute(right_image_topic)
        if camera_info_topic:
            self.topics["camera_info"] = _absolute(camera_info_topic)
            if "right" in self.topics:
                self.topics["right_camera_info"] = f"{self.topics['right'].removesuffix('/compressed').rsplit('/', 1)[0]}/camera_info"
        if odom_topic:
            self.topics["odom"] = _absolute(odom_topic)
        self.camera = camera
        self.camera_assumed = False
        # The intrinsics come with the stream (CameraInfo, or a camera assumed from the first image's size).
        self.camera_expected = camera is None
        self.camera_note = None if camera is not None else (
            f"from {self.topics['camera_info']} (sensor_msgs/CameraInfo) when it arrives" if camera_info_topic else
            f"assumed when the first image arrives: a pinhole with a {fov or DEFAULT_FOV_DEG:g}° horizontal field of view")
        self.image_size: tuple[int, int] | None = None
        self._fov = fov
        self._grey = grey
        self._tolerance_ns = int(round(stereo_tolerance * 1e9))
        self._start, self._stop, self._step = start, stop, step
        self._condition = threading.Condition()
        self._slot: tuple | None = None          # the newest frame not taken: (seq, stamp ns, left, right)
        self._lefts: collections.deque = collections.deque(maxlen=PAIRS_WAITING)    # (seq, stamp, msgtype, cdr)
        self._rights: collections.deque = collections.deque(maxlen=PAIRS_WAITING)   # (stamp, msgtype, cdr)
        self._infos: dict[str, object] = {}
        self._odometry: collections.deque = collections.deque(maxlen=ODOMETRY_KEPT)  # (stamp ns, x, y, yaw)
        self._heard = 0
        self._anchor: np.ndarray | None = None
        self._previous_pose: np.ndarray | None = None
        self.frames_dropped = 0
        self.frames_waiting = 0                   # frames given up for want of CameraInfo or odometry
        self.counters = {name: 0 for name in BAD_INPUTS}
        self._logged: set[tuple[str, str]] = set()
        self._stopping: threading.Event | None = None
        self._closed = False

    # ----------------------------------------------------------------- the session side
    def subscriptions(self) -> list[tuple[str, str, tuple[str, ...]]]:
        """(role, topic, types) to subscribe to; samples go to `on_sample(role, ...)`."""
        types = {"image": IMAGE_TYPES, "right": IMAGE_TYPES, "camera_info": (CAMERA_INFO_TYPE,),
                 "right_camera_info": (CAMERA_INFO_TYPE,), "odom": (ODOMETRY_TYPE,)}
        return [(role, topic, _bridge_first(types[role], topic)) for role, topic in self.topics.items()]

    def bind(self, stopping: threading.Event) -> None:
        """Iteration ends when `stopping` is set (the service is stopping)."""
        self._stopping = stopping

    def on_sample(self, role: str, key: str, msgtype: str, cdr: bytes, attachment_ok: bool | None) -> None:
        """One sample of `role`'s topic (a Zenoh thread). `attachment_ok`: False when rmw_zenoh's
        attachment is missing or malformed, None where none is expected (bridge keys)."""
        expected = IMAGE_TYPES if role in ("image", "right") else \
            (ODOMETRY_TYPE,) if role == "odom" else (CAMERA_INFO_TYPE,)
        if attachment_ok is False:
            return self._bad("no_attachment", key, "a sample without rmw_zenoh's attachment")
        if msgtype not in expected:
            return self._bad("unexpected_type", key, f"type {msgtype or 'unreadable from the key'}, expected "
                                                      f"{' or '.join(expected)}")
        if len(cdr) < 12 or cdr[:2] not in (b"\x00\x01", b"\x00\x00"):   # CDR little- or big-endian encapsulation
            return self._bad("malformed", key, f"{len(cdr)} bytes that are not CDR")
        if role in ("image", "right"):
            self._image(role, key, msgtype, cdr)
            return
        message = self._decode(key, msgtype, cdr)
        if message is None:
            return
        if role == "odom":
            q = message.pose.pose.orientation
            yaw = float(np.arctan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z)))
            with self._condition:
                self._odometry.append((header_stamp_ns(cdr), message.pose.pose.position.x, message.pose.pose.position.y, yaw))
        else:
            with self._condition:
                self._infos[role] = message

    def _decode(self, key: str, msgtype: str, cdr: bytes):
        try:
            return self.store.deserialize_cdr(cdr, msgtype)
        except Exception as error:   # rosbags raises several kinds on a payload cut short or garbled
            self._bad("malformed", key, f"CDR that does not decode as {msgtype} ({type(error).__name__}: {error})")
            return None

    def _bad(self, kind: str, key: str, what: str) -> None:
        self.counters[kind] += 1
        if (key, kind) not in self._logged:
            self._logged.add((key, kind))
            log.warning("source: dropped on %s: %s (counted as %s; said once per key)", key, what, kind)

    def _image(self, role: str, key: str, msgtype: str, cdr: bytes) -> None:
        message = self._decode(key, msgtype, cdr)   # (CDR only: the pixels are decoded for the frame taken)
        if message is None:
            return
        stamp = header_stamp_ns(cdr)
        with self._condition:
            if role == "image":
                self._lefts.append((self._heard, stamp, msgtype, message, key))
                self._heard += 1
            else:
                self._rights.append((stamp, msgtype, message, key))
            pair = self._pair()
            if pair is not None:
                if self._slot is not None:
                    self.frames_dropped += 1
                self._slot = pair
                self._condition.notify_all()

    def _pair(self):
        """The newest left image with its right partner (stereo) as the next frame, or None."""
        if "right" not in self.topics:
            if not self._lefts:
                return None
            newest = self._lefts.pop()
            self._lefts.clear()
            return newest + (None,)
        for index in range(len(self._lefts) - 1, -1, -1):
            seq, stamp, msgtype, message, key = self._lefts[index]
            right = min(self._rights, key=lambda r: abs(r[0] - stamp), default=None)
            if right is not None and abs(right[0] - stamp) <= self._tolerance_ns:
                for _ in range(index + 1):
                    self._lefts.popleft()
                while self._rights and self._rights[0][0] <= right[0]:
                    self._rights.popleft()
                return seq, stamp, msgtype, message, key, right
        return None

    # ----------------------------------------------------------------- the pipeline side
    def latest(self, timeout: float) -> Frame | None:
        """The newest frame not taken yet, within `timeout` seconds (None: none came, or it could not be used)."""
        with self._condition:
            if not self._condition.wait_for(lambda: self._slot is not None or self._closed, timeout) or self._slot is None:
                return None
            (seq, stamp, msgtype, message, key, right), self._slot = self._slot, None
            infos = dict(self._infos)
            odometry = list(self._odometry) if "odom" in self.topics else None
        images = []
        for role, (kind, decoded, where) in [("image", (msgtype, message, key))] + ([("right", right[1:])] if right else []):
            try:
                images.append(decode_image(decoded, kind, self.topics[role], self._grey))
                if len(images) == 2 and images[0].shape != images[1].shape:
                    raise SourceError(f"right image {images[1].shape[1]}×{images[1].shape[0]} does not match the left "
                                      f"{images[0].shape[1]}×{images[0].shape[0]}")
            except SourceError as error:
                self._bad("bad_image", where, str(error))
                return None
        if not self._set_camera(images[0], infos):
            return None
        truth, motion = self._odometry_at(stamp, odometry)
        if odometry is not None and truth is None:
            self._waiting(f"{self.topics['odom']} (nav_msgs/Odometry) covering the image's stamp")
            return None
        return Frame(seq=seq, stamp=stamp / 1e9, left=images[0], right=images[1] if len(images) > 1 else None,
                     camera=self.camera, ground_truth=truth, odometry=motion)

    def _set_camera(self, image: np.ndarray, infos: dict) -> bool:
        height, width = image.shape[:2]
        if self.image_size is not None and self.image_size != (width, height):
            self._bad("bad_image", self.topics["image"], f"an image of {width}×{height}, the stream's are "
                                                         f"{self.image_size[0]}×{self.image_size[1]}")
            return False
        self.image_size = (width, height)
        if self.camera is not None:
            return True
        if "camera_info" in self.topics:
            if "camera_info" not in infos:
                self._waiting(f"{self.topics['camera_info']} (sensor_msgs/CameraInfo)")
                return False
            self.camera = camera_from_info(infos["camera_info"], infos.get("right_camera_info"))
        else:
            self.camera = assumed_camera(width, height, self._fov or DEFAULT_FOV_DEG)
            self.camera_assumed = True
        return True

    def _waiting(self, what: str) -> None:
        self.frames_waiting += 1
        if self.frames_waiting == 1 or self.frames_waiting % 100 == 0:
            log.warning("source: %d frame(s) of %s given up waiting for %s", self.frames_waiting, self.topics["image"], what)

    def _odometry_at(self, stamp: int, odometry):
        """Ground truth (from the first frame's pose) and odometry (since the previous frame) at `stamp`."""
        if not odometry:
            return None, None
        odometry.sort()
        times = np.array([row[0] for row in odometry], dtype=float)
        poses = np.array([row[1:] for row in odometry], dtype=float)
        poses[:, 2] = np.unwrap(poses[:, 2])
        # A camera stamp just past the newest odometry takes the newest pose (no extrapolation).
        planar = interpolate_planar(times, poses, float(min(stamp, times[-1])))
        if planar is None:
            return None, None
        pose = camera_pose_of_planar(*planar)
        if self._anchor is None:
            self._anchor = np.linalg.inv(pose)
        truth = self._anchor @ pose
        motion = planar_motion(self._previous_pose, truth) if self._previous_pose is not None else (0.0, 0.0, 0.0)
        self._previous_pose = truth
        return truth, motion

    def __iter__(self) -> Iterator[Frame]:
        last = None
        said = time.monotonic()
        while not self._closed and not (self._stopping is not None and self._stopping.is_set()):
            frame = self.latest(0.1)
            if frame is None:
                if self._heard == 0 and time.monotonic() - said > WAIT_LOG_S:
                    said = time.monotonic()
                    log.info("source: no image on %s yet", self.topics["image"])
                continue
            if self._stop is not None and frame.seq >= self._stop:
                return
            if frame.seq < self._start or (last is not None and frame.seq - last < self._step):
                continue
            last = frame.seq
            yield frame
            if self._stop is not None and frame.seq + self._step >= self._stop:   # the last frame asked for
                return

    def __len__(self) -> int:
        if self._stop is None:
            raise TypeError(f"{self.name} is live: it has no length without a stop")
        return len(range(self._start, self._stop, self._step))

    def __getitem__(self, i: int) -> Frame:
        raise TypeError(f"{self.name} is live: iterate it, it has no indexed access")

    def close(self) -> None:
        with self._condition:
            self._closed = True
            self._condition.notify_all()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _absolute(topic: str) -> str:
    return "/" + topic.strip("/")


def _bridge_first(types: tuple[str, ...], topic: str) -> tuple[str, ...]:
    """The types of a topic, the likeliest first (on bridge keys the first is taken: image_transport
    names compressed images `.../compressed`)."""
    if types == IMAGE_TYPES and topic.endswith("/compressed"):
        return COMPRESSED_IMAGE_TYPE, IMAGE_TYPE
    return types
