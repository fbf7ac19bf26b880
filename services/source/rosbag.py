"""ROS bags as a frame source: ROS 1 ``.bag`` files and ROS 2 bags (a folder with
``metadata.yaml``, or a lone ``.db3`` / ``.mcap`` file), read with the pure-Python ``rosbags``
library, so no ROS installation is needed (the optional extra ``ros``).

What a bag gives:

- images from ``sensor_msgs/Image`` (mono8, 8UC1, bgr8, rgb8, bgra8, rgba8, 8UC3, mono16,
  16UC1) or ``sensor_msgs/CompressedImage`` (JPEG, PNG); 16-bit pixels keep their high byte;
- stereo: a right image topic, each left image paired with the right image whose header stamp
  is nearest, within ``stereo_tolerance`` seconds (a left image without one is left out, with
  one warning: its ``seq`` shows the gap);
- intrinsics from ``sensor_msgs/CameraInfo`` (the rectified projection P, else K), the stereo
  baseline from the right camera's P (ROS convention: P[0,3] = −fx·baseline), when no
  calibration file or preset gives them;
- ``nav_msgs/Odometry`` on ``odom_topic``: its planar pose, interpolated at each image's stamp,
  becomes ``Frame.ground_truth`` (re-anchored at the first selected frame, camera convention)
  and ``Frame.odometry`` (the motion since the previous selected frame), which the passthrough
  estimator uses.

``seq`` is the image's index on the left topic in stamp order, ``stamp`` its header stamp in
seconds (the bag's record time where the header has none). Opening reads the bag once to index
the stamps (the images' data is read then, not decoded); iteration then streams the bag once
more, and indexed access reads one message through the bag's index.
"""

from __future__ import annotations

import bisect
import dataclasses
import importlib
import logging
import math
import struct
from pathlib import Path
from typing import Any, Iterator

import cv2
import numpy as np

from services.source.datasets import IndexedSource
from services.common.geometry import planar_motion
from services.common.frames import Camera, Frame, SourceError

log = logging.getLogger(__name__)

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
# Raw encodings read (sensor_msgs/image_encodings names): channels and bytes per channel.
RAW_ENCODINGS = {"mono8": (1, 1), "8UC1": (1, 1), "bgr8": (3, 1), "rgb8": (3, 1), "8UC3": (3, 1), "bgra8": (4, 1),
                 "rgba8": (4, 1), "mono16": (1, 2), "16UC1": (1, 2)}
COMPRESSED_FORMATS = ("jpeg", "jpg", "png")
# Stereo cameras are triggered together: their stamps differ by far less than a frame period.
DEFAULT_STEREO_TOLERANCE_S = 0.005
# Iteration holds the images read ahead of the next frame due (a right image recorded before its
# left one); beyond this many, the frame due is taken as lost (one of its messages did not decode).
MAX_WAITING = 64
MCAP_MAGIC = b"\x89MCAP0\r\n"


def _import_rosbags():
    try:
        from rosbags.highlevel import AnyReader, AnyReaderError
    except ImportError:
        raise SourceError("reading ROS bags needs the optional extra 'ros': pip install 'gridslam[ros]'") from None
    return AnyReader, AnyReaderError


def _read_errors() -> tuple[type[BaseException], ...]:
    """The exceptions a damaged bag raises while its messages are read."""
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error

    errors: list[type[BaseException]] = [AnyReaderError, Reader1Error, Reader2Error, EOFError, struct.error]
    for module, name in (("mcap.exceptions", "McapError"), ("apsw", "Error")):   # the storages' own
        try:
            errors.append(getattr(importlib.import_module(module), name))
        except (ImportError, AttributeError):
            pass
    return tuple(errors)


def _file_of(path: Path) -> Path:
    """The storage file of a bag: the .bag, .db3 or .mcap itself, or the one in a ROS 2 bag folder."""
    if path.is_dir():
        return next(iter(sorted(p for p in path.iterdir() if p.suffix in (".db3", ".mcap"))), path)
    return path


def damage(path: Path, error: BaseException) -> SourceError:
    """One line for a bag that cannot be read: where it ends or breaks, by byte offset when the
    format tells it (a ROS 1 bag's header holds its index position; an MCAP file ends in a magic)."""
    file = _file_of(path)
    size = file.stat().st_size if file.is_file() else 0
    where = ""
    if file.suffix == ".bag" and size:
        index = _ros1_index_position(file)
        if index is not None and index >= size:
            where = (f"the index should start at byte {index} but the file ends at byte {size}: "
                     "truncated (`rosbag reindex` rebuilds the index)")
        elif index is not None:
            where = (f"the index from byte {index} is cut off or damaged (the file ends at byte {size}; "
                     "`rosbag reindex` rebuilds it)")
    elif file.suffix == ".mcap" and size:
        with file.open("rb") as stream:
            stream.seek(max(0, size - 8))
            if stream.read(8) != MCAP_MAGIC:
                where = f"the file ends at byte {size} without MCAP's closing magic: truncated"
    size_note = f"; the file is {size} bytes" if file.is_file() else ""
    return SourceError(f"{file}: {where or f'not a readable ROS bag ({_describe(error)}{size_note})'}")


def _ros1_index_position(file: Path) -> int | None:
    """`index_pos` of a ROS 1 bag's header record ("#ROSBAG V2.0\n", then fields name=value)."""
    with file.open("rb") as stream:
        if stream.read(13) != b"#ROSBAG V2.0\n":
            return None
        (length,) = struct.unpack("<I", stream.read(4))
        fields, offset = stream.read(length), 0
        while offset + 4 <= len(fields):
            (size,) = struct.unpack_from("<I", fields, offset)
            name, _, value = fields[offset + 4:offset + 4 + size].partition(b"=")
            if name == b"index_pos" and len(value) == 8:
                return struct.unpack("<Q", value)[0]
            offset += 4 + size
    return None


def _stamp_ns(header, fallback_ns: int) -> int:
    stamp = header.stamp
    ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    return ns if ns > 0 else fallback_ns


def _field(message, name: str):
    """A CameraInfo matrix by its ROS 2 (k, p) or ROS 1 (K, P) name."""
    value = getattr(message, name, None)
    return getattr(message, name.upper()) if value is None else value


def camera_from_info(left, right=None) -> Camera:
    """Intrinsics from a left (and right) CameraInfo: the rectified projection P when set, else K."""
    p, k = np.asarray(_field(left, "p"), dtype=float), np.asarray(_field(left, "k"), dtype=float)
    fx, fy, cx, cy = (p[0], p[5], p[2], p[6]) if p.size == 12 and p[0] > 0 else (k[0], k[4], k[2], k[5])
    baseline = 0.0
    if right is not None:
        p_right = np.asarray(_field(right, "p"), dtype=float)
        if p_right.size == 12 and p_right[0] > 0:
            baseline = max(0.0, -p_right[3] / p_right[0])
    return Camera(fx=float(fx), fy=float(fy), cx=float(cx), cy=float(cy), baseline=float(baseline),
                  width=int(left.width), height=int(left.height))


def decode_image(message, msgtype: str, topic: str, grey: bool) -> np.ndarray:
    """An 8-bit H×W grey or H×W×3 BGR image from an Image or CompressedImage message."""
    if msgtype == "sensor_msgs/msg/CompressedImage":
        fmt = message.format.lower()
        if "compresseddepth" in fmt or not any(name in fmt for name in COMPRESSED_FORMATS):
            raise SourceError(f"topic {topic}: compressed image format {message.format!r} is not supported "
                              f"(JPEG or PNG)")
        data = np.asarray(message.data, dtype=np.uint8)
        # As the image folders read their files (datasets.read_image).
        image = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_UNCHANGED) if data.size else None
        if image is None:
            raise SourceError(f"topic {topic}: a {message.format!r} image that does not decode")
    else:
        encoding = message.encoding
        if encoding not in RAW_ENCODINGS:
            raise SourceError(f"topic {topic}: image encoding {encoding!r} is not supported "
                              f"({', '.join(RAW_ENCODINGS)})")
        channels, depth = RAW_ENCODINGS[encoding]
        height, width, step = int(message.height), int(message.width), int(message.step)
        data = np.asarray(message.data, dtype=np.uint8)
        if step < width * channels * depth or data.size < step * height:
            raise SourceError(f"topic {topic}: {encoding} image of {width}×{height} with step {step} "
                              f"has {data.size} bytes")
        rows = data[:step * height].reshape(height, step)[:, :width * channels * depth]
        if depth == 2:
            rows = rows.view(">u2" if message.is_bigendian else "<u2")
        image = rows.reshape(height, width, channels) if channels > 1 else rows.reshape(height, width)
        if encoding in ("rgb8", "rgba8"):
            image = image[..., [2, 1, 0]]
    if image.dtype != np.uint8:   # 16-bit: the high byte
        image = (image >> 8).astype(np.uint8)
    if image.ndim == 3 and image.shape[2] == 4:
        image = image[..., :3]
    if grey and image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)   # ITU-R 601 luma, as the other sources
    return np.ascontiguousarray(image)


@dataclasses.dataclass(frozen=True)
class _Image:
    """An image message as indexed: its header stamp and the bag's record time, ns."""

    stamp: int
    record: int


def camera_pose_of_planar(x: float, y: float, yaw: float) -> np.ndarray:
    """A planar pose (x forward, y left, yaw counter-clockwise) as a 4×4 camera pose in the
    camera convention (x right, y down, z forward), as ``Frame.ground_truth`` holds it."""
    c, s = math.cos(yaw), math.sin(yaw)
    pose = np.eye(4)
    pose[:3, :3] = [[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]]
    pose[0, 3], pose[2, 3] = -y, x
    return pose


def interpolate_planar(times: np.ndarray, poses: np.ndarray, at: float) -> tuple[float, float, float] | None:
    """The planar pose (x, y, yaw) at time `at`, linear between the two poses around it (yaw
    unwrapped); None outside the poses' time span."""
    if len(times) == 0 or at < times[0] or at > times[-1]:
        return None
    i = int(np.searchsorted(times, at, side="left"))
    if times[i] == at or i == 0:
        return tuple(float(v) for v in poses[i])
    t0, t1 = times[i - 1], times[i]
    w = (at - t0) / (t1 - t0)
    return tuple(float(a + w * (b - a)) for a, b in zip(poses[i - 1], poses[i]))


class RosbagSource(IndexedSource):
    """Frames from a ROS 1 or ROS 2 bag (module docstring). ``image_topic`` may be left out when
    the bag has one image topic; ``camera_info_topic`` defaults to the image topic's sibling
    ``camera_info`` (``/cam/image_raw/compressed`` → ``/cam/camera_info``) when the bag has it,
    and so does the right camera's."""

    def __init__(
        self,
        path: str | Path,
        *,
        image_topic: str | None = None,
        right_image_topic: str | None = None,
        camera_info_topic: str | None = None,
        odom_topic: str | None = None,
        stereo_tolerance: float = DEFAULT_STEREO_TOLERANCE_S,
        start: int = 0,
        stop: int | None = None,
        step: int = 1,
        camera: Camera | None = None,
        grey: bool = False,
        mono: bool = False,
        origin: int | None = None,
    ):
        AnyReader, AnyReaderError = _import_rosbags()
        self._path = Path(path)
        if not self._path.exists():
            raise SourceError(f"{self._path}: ROS bag not found")
        self._grey = grey
        self._reader = None
        try:
            self._reader = AnyReader([self._path])
            self._reader.open()
        except (AnyReaderError, *_read_errors(), OSError) as error:   # a folder without metadata.yaml is an OSError
            raise damage(self._path, error) from None
        try:
            self._open(image_topic, None if mono else right_image_topic, camera_info_topic, odom_topic,
                       stereo_tolerance, camera, origin, start, stop, step)
        except BaseException:
            self.close()
            raise

    # ----------------------------------------------------------------- indexing
    def _open(self, image_topic, right_topic, info_topic, odom_topic, tolerance, camera, origin, start, stop, step):
        topics = self._reader.topics
        image_topics = sorted(name for name, info in topics.items() if info.msgtype in IMAGE_TYPES)
        if image_topic is None:
            if len(image_topics) != 1:
                raise SourceError(f"{self._path}: choose the camera with --image-topic (image topics: "
                                  f"{', '.join(image_topics) or 'none'})")
            image_topic = image_topics[0]
        self.topics = {"image": self._topic(image_topic, IMAGE_TYPES, image_topics, "image")}
        if right_topic:
            self.topics["right"] = self._topic(right_topic, IMAGE_TYPES, image_topics, "image")
        infos = sorted(name for name, info in topics.items() if info.msgtype == CAMERA_INFO_TYPE)
        if info_topic:
            self.topics["camera_info"] = self._topic(info_topic, (CAMERA_INFO_TYPE,), infos, "CameraInfo")
        elif _sibling_info(image_topic) in infos:
            self.topics["camera_info"] = _sibling_info(image_topic)
        if right_topic and _sibling_info(right_topic) in infos:
            self.topics["right_camera_info"] = _sibling_info(right_topic)
        if odom_topic:
            odometries = sorted(name for name, info in topics.items() if info.msgtype == ODOMETRY_TYPE)
            self.topics["odom"] = self._topic(odom_topic, (ODOMETRY_TYPE,), odometries, "Odometry")
        self._msgtypes = {role: topics[name].msgtype for role, name in self.topics.items()}
        self._connections = {role: [c for c in self._reader.connections if c.topic == name]
                             for role, name in self.topics.items()}
        index = self._index()
        lefts = sorted(index["image"], key=lambda image: image.stamp)
        if not lefts:
            raise SourceError(f"{self._path}: topic {self.topics['image']} has no messages")
        self._lefts = lefts
        self._rights: dict[int, _Image] = {}
        seqs = list(range(len(lefts)))
        if right_topic:
            rights = sorted(index["right"], key=lambda image: image.stamp)
            stamps = [image.stamp for image in rights]
            limit = int(round(tolerance * 1e9))
            for seq, left in enumerate(lefts):
                i = bisect.bisect_left(stamps, left.stamp)
                near = min((j for j in (i - 1, i) if 0 <= j < len(rights)), key=lambda j: abs(stamps[j] - left.stamp),
                           default=None)
                if near is not None and abs(stamps[near] - left.stamp) <= limit:
                    self._rights[seq] = rights[near]
            seqs = sorted(self._rights)
            if not seqs:
                raise SourceError(f"{self._path}: no image of {right_topic} within {tolerance} s of one of "
                                  f"{self.topics['image']}")
            if len(seqs) < len(lefts):
                log.warning("%s: %d of %d images of %s have no image of %s within %g s; left out", self._path,
                            len(lefts) - len(seqs), len(lefts), self.topics["image"], right_topic, tolerance)
        if camera is None and index.get("camera_info"):
            camera = camera_from_info(index["camera_info"][0], (index.get("right_camera_info") or [None])[0])
        selected = seqs[start:stop:step]
        self._ground_truth, self._odometry = self._poses(index.get("odom"), selected, origin)
        super().__init__(str(self._path), seqs, camera, start, stop, step)

    def _topic(self, name: str, types: tuple[str, ...], candidates: list[str], kind: str) -> str:
        info = self._reader.topics.get(name)
        if info is None:
            raise SourceError(f"{self._path}: no topic {name} ({kind} topics: {', '.join(candidates) or 'none'})")
        if info.msgtype not in types:
            raise SourceError(f"{self._path}: topic {name} is {info.msgtype}, expected {' or '.join(types)}")
        return name

    def _index(self) -> dict[str, list]:
        """One pass over the bag: the stamps of the images, the first CameraInfo of each
        camera, every odometry pose (stamp, x, y, yaw)."""
        role_of = {connection.id: role for role, connections in self._connections.items() for connection in connections}
        wanted = [connection for connections in self._connections.values() for connection in connections]
        index: dict[str, list] = {role: [] for role in self.topics}
        for connection, record, raw in self._messages(wanted):
            role = role_of[connection.id]
            if role in ("camera_info", "right_camera_info"):
                if not index[role]:
                    index[role].append(self._deserialize(raw, connection))
                continue
            message = self._deserialize(raw, connection)
            stamp = _stamp_ns(message.header, record)
            if role == "odom":
                q = message.pose.pose.orientation
                yaw = math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
                index[role].append((stamp, message.pose.pose.position.x, message.pose.pose.position.y, yaw))
            else:
                index[role].append(_Image(stamp, record))
        return index

    def _poses(self, odometry: list | None, selected: list[int], origin: int | None):
        """Ground truth and odometry of the selected frames from the odometry topic (None without one)."""
        if odometry is None:
            return {}, {}
        if not odometry:
            raise SourceError(f"{self._path}: topic {self.topics['odom']} has no messages")
        odometry.sort()
        times = np.array([row[0] for row in odometry], dtype=float)
        poses = np.array([row[1:] for row in odometry], dtype=float)
        poses[:, 2] = np.unwrap(poses[:, 2])
        planar = {seq: interpolate_planar(times, poses, float(self._lefts[seq].stamp)) for seq in selected}
        if origin is not None and 0 <= origin < len(self._lefts):
            anchor = interpolate_planar(times, poses, float(self._lefts[origin].stamp))
        else:
            anchor = next((pose for pose in planar.values() if pose is not None), None)
        missing = sum(pose is None for pose in planar.values())
        if missing:
            log.warning("%s: %d of %d frames lie outside the time span of %s: they have no odometry", self._path,
                        missing, len(selected), self.topics["odom"])
        if anchor is None:
            return {}, {}
        inverse_anchor = np.linalg.inv(camera_pose_of_planar(*anchor))
        truth = {seq: inverse_anchor @ camera_pose_of_planar(*pose) for seq, pose in planar.items() if pose is not None}
        motion, previous = {}, None
        for seq in selected:
            if seq in truth:
                motion[seq] = planar_motion(truth[previous], truth[seq]) if previous in truth else (0.0, 0.0, 0.0)
            previous = seq
        return truth, motion

    # ----------------------------------------------------------------- reading
    def _messages(self, connections, start: int | None = None, stop: int | None = None):
        try:
            yield from self._reader.messages(connections=connections, start=start, stop=stop)
        except _read_errors() as error:
            raise damage(self._path, error) from None

    def _deserialize(self, raw, connection):
        try:
            return self._reader.deserialize(raw, connection.msgtype)
        except _read_errors() as error:
            raise SourceError(f"{self._path}: topic {connection.topic}: a message that does not decode "
                              f"({_describe(error)})") from None

    def _frame(self, seq: int, left, right) -> Frame:
        images = []
        for role, message in (("image", left), ("right", right)):
            if message is None:
                continue
            image = decode_image(message, self._msgtypes[role], self.topics[role], self._grey)
            self._check_size(image, self._path)
            images.append(image)
        if len(images) == 2 and images[0].shape != images[1].shape:
            raise SourceError(f"{self._path}: frame {seq}: right image {images[1].shape[1]}×{images[1].shape[0]} "
                              f"does not match the left {images[0].shape[1]}×{images[0].shape[0]}")
        return Frame(seq=seq, stamp=self._lefts[seq].stamp / 1e9, left=images[0], right=images[1] if right else None,
                     camera=self.camera, ground_truth=self._ground_truth.get(seq), odometry=self._odometry.get(seq))

    def _find(self, role: str, image: _Image):
        """The message of `role` with this header stamp, read through the bag's index."""
        for connection, record, raw in self._messages(self._connections[role], image.record, image.record + 1):
            message = self._deserialize(raw, connection)
            if _stamp_ns(message.header, record) == image.stamp:
                return message
        raise SourceError(f"{self._path}: topic {self.topics[role]}: the message stamped {image.stamp / 1e9:.9f} "
                          f"is gone")

    def _read(self, seq: int) -> Frame:
        right = self._find("right", self._rights[seq]) if "right" in self.topics else None
        return self._frame(seq, self._find("image", self._lefts[seq]), right)

    def __iter__(self) -> Iterator[Frame]:
        """One pass over the image topics, frames in order; an undecodable frame is skipped with a warning."""
        stereo = "right" in self.topics
        wanted_left = {self._lefts[seq].stamp: seq for seq in self._seqs}
        wanted_right = {self._rights[seq].stamp: seq for seq in self._seqs} if stereo else {}
        lefts: dict[int, Any] = {}
        rights: dict[int, Any] = {}
        pending = list(self._seqs)   # in order; the first is yielded as soon as its messages are in
        roles = {connection.id: role for role in ("image", "right") for connection in self._connections.get(role, [])}
        connections = self._connections["image"] + (self._connections["right"] if stereo else [])
        position = 0
        for connection, record, raw in self._messages(connections):
            role = roles[connection.id]
            try:
                message = self._deserialize(raw, connection)
            except SourceError as error:
                log.warning("message skipped: %s", error)
                continue
            stamp = _stamp_ns(message.header, record)
            seq = (wanted_left if role == "image" else wanted_right).get(stamp)
            if seq is None:
                continue
            (lefts if role == "image" else rights)[seq] = message
            while len(lefts) + len(rights) > MAX_WAITING and position < len(pending):
                if pending[position] not in lefts or stereo and pending[position] not in rights:   # one did not decode
                    log.warning("frame %d skipped: %s: an image of it was not read", pending[position], self._path)
                    lefts.pop(pending[position], None)
                    rights.pop(pending[position], None)
                    position += 1
                else:
                    break
            while position < len(pending) and pending[position] in lefts and (not stereo or pending[position] in rights):
                ready = pending[position]
                position += 1
                try:
                    frame = self._frame(ready, lefts.pop(ready), rights.pop(ready, None))
                except SourceError as error:
                    log.warning("frame %d skipped: %s", ready, error)
                    continue
                yield frame
        for seq in pending[position:]:
            log.warning("frame %d skipped: %s: its image messages were not found on a second reading", seq, self._path)

    def close(self) -> None:
        if getattr(self, "_reader", None) is not None and self._reader.stack is not None:
            self._reader.close()


def _sibling_info(image_topic: str) -> str:
    """``/cam/image_raw`` and ``/cam/image_raw/compressed`` → ``/cam/camera_info`` (image_transport's layout)."""
    base = image_topic.removesuffix("/compressed")
    return f"{base.rsplit('/', 1)[0]}/camera_info"


def _describe(error: BaseException) -> str:
    return str(error) or type(error).__name__
