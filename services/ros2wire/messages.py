"""The ROS 2 messages of a gridslam run, serialised to CDR (ROS 2's wire and bag encoding) with
the message definitions of a ROS 2 distribution from the `rosbags` type store (optional extra
`ros`; Humble's for files, the node's distribution live). Pure: numbers and arrays in, bytes
out. This is the one place where gridslam's numbers become ROS 2 messages: the MCAP writer, the
Foxglove server and the live ROS 2 node (node.py) all publish what it makes, so a recorded run
and a live one look the same.

Topics (docs/ecosystem.md):

| topic | type | from |
|---|---|---|
| /gridslam/egomotion, /gridslam/gridcells, /gridslam/map, /gridslam/groundtruth | nav_msgs/Odometry | each stage's pose |
| /tf | tf2_msgs/TFMessage | map → each stage's body frame, with every pose |
| /tf_static | tf2_msgs/TFMessage | base_link → camera (optical axes) |
| /gridslam/map/markers | visualization_msgs/MarkerArray | the experience map |
| /gridslam/loop_closure | std_msgs/String | a confirmed closure, as JSON |
| /gridslam/camera/image/compressed | sensor_msgs/CompressedImage | the left camera image, JPEG |
| /gridslam/camera/camera_info | sensor_msgs/CameraInfo | its intrinsics |
| /gridslam/grid/activity | sensor_msgs/Image | the grid-cell sheet's activity, mono8 |

Frames: every stage starts at the origin of `map` heading along +x (as in the viewer), so all
four Odometry topics are in `map` and compare as they are; each has its own body frame
(`base_link` is the map stage's, the corrected pose; `gridcells_base_link`,
`egomotion_base_link`, `groundtruth_base_link`), so that a 3-D panel can follow any of them.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass, field

import numpy as np

from services.common.observe import CLOSURE_KEPT, CLOSURE_REFUSED, ODOMETRIC
from services.common.errors import ConfigError
from services.common.images import display_image, encode_camera_jpeg

ODOMETRY = "nav_msgs/msg/Odometry"
TF = "tf2_msgs/msg/TFMessage"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
STRING = "std_msgs/msg/String"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMAGE = "sensor_msgs/msg/Image"

# Stage → (topic, body frame). The stages are those of the results folder's TUM files, with
# `map` the pose expmap published at each frame (map_online.tum).
STAGES = {
    "egomotion": ("/gridslam/egomotion", "egomotion_base_link"),
    "gridcells": ("/gridslam/gridcells", "gridcells_base_link"),
    "map": ("/gridslam/map", "base_link"),
    "groundtruth": ("/gridslam/groundtruth", "groundtruth_base_link"),
}
MAP_FRAME = "map"
CAMERA_FRAME = "camera"
GRID_FRAME = "grid"
MARKERS_TOPIC = "/gridslam/map/markers"
CLOSURE_TOPIC = "/gridslam/loop_closure"
CAMERA_TOPIC = "/gridslam/camera/image/compressed"
CAMERA_INFO_TOPIC = "/gridslam/camera/camera_info"
ACTIVITY_TOPIC = "/gridslam/grid/activity"
PATH = "nav_msgs/msg/Path"
POSE_WITH_COVARIANCE = "geometry_msgs/msg/PoseWithCovarianceStamped"
ROUTE_TOPIC = "/gridslam/route"   # a route planned on the map (gridslam map route)
TOPICS: dict[str, str] = {
    **{topic: ODOMETRY for topic, _ in STAGES.values()},
    "/tf": TF,
    "/tf_static": TF,
    MARKERS_TOPIC: MARKER_ARRAY,
    CLOSURE_TOPIC: STRING,
    CAMERA_TOPIC: COMPRESSED_IMAGE,
    CAMERA_INFO_TOPIC: CAMERA_INFO,
    ACTIVITY_TOPIC: IMAGE,
    ROUTE_TOPIC: PATH,
}
# Optical axes (z forward, x right, y down) in the body frame (x forward, y left, z up):
# REP 103's camera "_optical" rotation, as a quaternion (x, y, z, w).
OPTICAL_ROTATION = (-0.5, 0.5, -0.5, 0.5)

# Camera images are recorded as JPEG at most this wide (a KITTI frame becomes 640×194).
CAMERA_MAX_WIDTH = 640
CAMERA_JPEG_QUALITY = 85
# Marker colours (r, g, b, a): the viewer's palette.
COLOURS = {"experiences": (0.42, 0.25, 0.71, 0.9), ODOMETRIC: (0.42, 0.25, 0.71, 0.45),
           CLOSURE_KEPT: (0.88, 0.2, 0.1, 1.0), CLOSURE_REFUSED: (0.55, 0.55, 0.55, 0.8)}
LINK_NAMESPACES = {ODOMETRIC: "links", CLOSURE_KEPT: "closures", CLOSURE_REFUSED: "closures_refused"}


class RosUnavailable(ConfigError):
    """The optional extra `ros` (rosbags, mcap) is not installed."""


# ROS 2 distribution → rosbags' type store of its message definitions (rolling: the newest).
DISTRO_STORES = {"humble": "ROS2_HUMBLE", "jazzy": "ROS2_JAZZY", "kilted": "ROS2_KILTED", "rolling": "LATEST"}


def typestore(distro: str = "humble"):
    """rosbags' type store of a ROS 2 distribution (Humble's for files: every later one reads
    them); RosUnavailable without the extra."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise RosUnavailable("ROS messages need the optional extra 'ros': pip install 'gridslam[ros]'") from None
    return get_typestore(getattr(Stores, DISTRO_STORES[distro]))


def yaw_quaternion(heading: float) -> tuple[float, float, float, float]:
    """A heading counter-clockwise about z as a quaternion (x, y, z, w)."""
    return 0.0, 0.0, math.sin(heading / 2), math.cos(heading / 2)


def planar_covariance_6x6(covariance) -> np.ndarray:
    """A planar (x, y, yaw) 3×3 covariance in the 6×6 (x, y, z, roll, pitch, yaw) layout of
    geometry_msgs/PoseWithCovariance, row-major; z, roll and pitch are held (variance 0)."""
    planar = np.asarray(covariance, dtype=float).reshape(3, 3)
    full = np.zeros((6, 6))
    index = [0, 1, 5]
    full[np.ix_(index, index)] = planar
    return full.reshape(36)


@dataclass
class MapState:
    """The experience map as far as it is drawn: experience id → (x, y), link (source, target) → kind."""

    experiences: dict[int, tuple[float, float]] = field(default_factory=dict)
    links: dict[tuple[int, int], int] = field(default_factory=dict)

    def apply(self, experiences, links) -> bool:
        """Experiences created or moved `(id, x, y)` and links created `(source, target, kind)`;
        True when something changed."""
        changed = False
        for experience_id, x, y in experiences:
            changed |= self.experiences.get(experience_id) != (x, y)
            self.experiences[experience_id] = (x, y)
        for source, target, kind in links:
            changed |= self.links.get((source, target)) != kind
            self.links[(source, target)] = kind
        return changed


def camera_jpeg(pixels: np.ndarray, encoding: str, max_width: int = CAMERA_MAX_WIDTH) -> tuple[bytes, float]:
    """A camera image as JPEG, at most `max_width` wide; and the scale applied to it (for the intrinsics)."""
    image = display_image(pixels, encoding, max_width)
    return encode_camera_jpeg(image, CAMERA_JPEG_QUALITY), image.shape[1] / pixels.shape[1]


def stamp_ns(seconds: float) -> int:
    """A source stamp in seconds as integer nanoseconds (MCAP's and ROS 2's time)."""
    return int(round(seconds * 1e9))


class RosMessages:
    """Builds and serialises the messages of the topics above."""

    def __init__(self, distro: str = "humble"):
        self.store = typestore(distro)
        self.types = self.store.types
        self._camera_info: tuple[tuple, bytes] | None = None   # (intrinsics, CameraInfo bytes stamped 0)

    def msgdef(self, msgtype: str) -> str:
        """The ROS 2 `.msg` definition text (with its dependencies) of `msgtype`, as bags embed it."""
        return self.store.generate_msgdef(msgtype, ros_version=2)[0]

    def rihs01(self, msgtype: str) -> str:
        """The RIHS01 type hash (REP-2016) of `msgtype`'s definition in this distribution."""
        return self.store.hash_rihs01(msgtype)

    # ------------------------------------------------------------------- building blocks
    def _time(self, stamp: int):
        return self.types["builtin_interfaces/msg/Time"](sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000)

    def _header(self, stamp: int, frame_id: str):
        return self.types["std_msgs/msg/Header"](stamp=self._time(stamp), frame_id=frame_id)

    def _vector(self, x=0.0, y=0.0, z=0.0):
        return self.types["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))

    def _quaternion(self, x=0.0, y=0.0, z=0.0, w=1.0):
        return self.types["geometry_msgs/msg/Quaternion"](x=float(x), y=float(y), z=float(z), w=float(w))

    def _serialize(self, message, msgtype: str) -> bytes:
        return bytes(self.store.serialize_cdr(message, msgtype))

    # ------------------------------------------------------------------- messages
    def poses(self, stamp: int, poses) -> list[tuple[str, bytes]]:
        """Stages' poses at one stamp, `[(stage, position (x, y, z), orientation (x, y, z, w))]`:
        each stage's Odometry, and one /tf message with the transform from `map` to each body frame."""
        messages, transforms = [], []
        for stage, position, orientation in poses:
            topic, body = STAGES[stage]
            messages.append((topic, self.odometry(stamp, MAP_FRAME, body, position, orientation)))
            transforms.append((MAP_FRAME, body, position, orientation))
        if transforms:
            messages.append(("/tf", self.transforms(stamp, transforms)))
        return messages

    def _pose(self, position, orientation):
        T = self.types
        point = T["geometry_msgs/msg/Point"](x=float(position[0]), y=float(position[1]), z=float(position[2]))
        return T["geometry_msgs/msg/Pose"](position=point, orientation=self._quaternion(*orientation))

    def odometry(self, stamp: int, frame_id: str, child_frame_id: str, position, orientation, covariance=None,
                 linear=(0.0, 0.0, 0.0), angular=(0.0, 0.0, 0.0)) -> bytes:
        """nav_msgs/Odometry: a pose in `frame_id` of `child_frame_id` with its 6×6 covariance
        (row-major, zeros: unknown) and the body-frame twist."""
        T = self.types
        covariance = np.zeros(36) if covariance is None else np.asarray(covariance, dtype=float).reshape(36)
        message = T[ODOMETRY](
            header=self._header(stamp, frame_id), child_frame_id=child_frame_id,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=self._pose(position, orientation), covariance=covariance),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=self._vector(*linear), angular=self._vector(*angular)),
                covariance=np.zeros(36)))
        return self._serialize(message, ODOMETRY)

    def transforms(self, stamp: int, transforms) -> bytes:
        """tf2_msgs/TFMessage of `[(parent, child, translation (x, y, z), rotation (x, y, z, w))]`."""
        return self._serialize(self.types[TF](transforms=[self._transform(stamp, *transform)
                                                          for transform in transforms]), TF)

    def pose_with_covariance(self, stamp: int, frame_id: str, position, orientation, covariance=None) -> bytes:
        """geometry_msgs/PoseWithCovarianceStamped (covariance 6×6 row-major; zeros: unknown)."""
        T = self.types
        covariance = np.zeros(36) if covariance is None else np.asarray(covariance, dtype=float).reshape(36)
        message = T[POSE_WITH_COVARIANCE](header=self._header(stamp, frame_id), pose=T["geometry_msgs/msg/PoseWithCovariance"](
            pose=self._pose(position, orientation), covariance=covariance))
        return self._serialize(message, POSE_WITH_COVARIANCE)

    def path(self, stamp: int, frame_id: str, poses) -> bytes:
        """nav_msgs/Path of `[(stamp ns, x, y, heading)]`, planar poses in `frame_id`."""
        T = self.types
        stamped = [T["geometry_msgs/msg/PoseStamped"](header=self._header(at, frame_id),
                                                      pose=self._pose((x, y, 0.0), yaw_quaternion(heading)))
                   for at, x, y, heading in poses]
        return self._serialize(T[PATH](header=self._header(stamp, frame_id), poses=stamped), PATH)

    def planar_pose(self, stage: str, stamp: int, x: float, y: float, heading: float) -> list[tuple[str, bytes]]:
        """One stage's planar pose (heading counter-clockwise about z): its Odometry and /tf."""
        return self.poses(stamp, [(stage, (x, y, 0.0), yaw_quaternion(heading))])

    def _transform(self, stamp: int, parent: str, child: str, translation, rotation):
        T = self.types
        return T["geometry_msgs/msg/TransformStamped"](
            header=self._header(stamp, parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](translation=self._vector(*translation), rotation=self._quaternion(*rotation)))

    def static_transforms(self, stamp: int) -> tuple[str, bytes]:
        """/tf_static: the camera's optical frame on the corrected body frame."""
        return "/tf_static", self.transforms(stamp, [(STAGES["map"][1], CAMERA_FRAME, (0.0, 0.0, 0.0), OPTICAL_ROTATION)])

    def camera_image(self, stamp: int, jpeg: bytes) -> tuple[str, bytes]:
        message = self.types[COMPRESSED_IMAGE](header=self._header(stamp, CAMERA_FRAME), format="jpeg",
                                               data=np.frombuffer(jpeg, dtype=np.uint8))
        return CAMERA_TOPIC, self._serialize(message, COMPRESSED_IMAGE)

    def camera_info(self, stamp: int, fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> tuple[str, bytes]:
        """A rectified pinhole camera: K and P from the intrinsics, no distortion. Serialised once
        per camera and restamped: the header's stamp is the first field after CDR's 4-byte
        encapsulation header (int32 sec, uint32 nanosec, little-endian)."""
        key = (fx, fy, cx, cy, width, height)
        if self._camera_info is None or self._camera_info[0] != key:
            self._camera_info = (key, self._camera_info_message(fx, fy, cx, cy, width, height))
        data = bytearray(self._camera_info[1])
        struct.pack_into("<iI", data, 4, stamp // 1_000_000_000, stamp % 1_000_000_000)
        return CAMERA_INFO_TOPIC, bytes(data)

    def _camera_info_message(self, fx, fy, cx, cy, width, height) -> bytes:
        T = self.types
        message = T[CAMERA_INFO](
            header=self._header(0, CAMERA_FRAME), height=int(height), width=int(width), distortion_model="plumb_bob",
            d=np.zeros(5), k=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], dtype=float), r=np.eye(3).reshape(9),
            p=np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], dtype=float), binning_x=0, binning_y=0,
            roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
        return self._serialize(message, CAMERA_INFO)

    def activity(self, stamp: int, pixels: np.ndarray) -> tuple[str, bytes]:
        """The grid-cell activity image, mono8."""
        return ACTIVITY_TOPIC, self.mono_image(stamp, GRID_FRAME, pixels)

    def mono_image(self, stamp: int, frame_id: str, pixels: np.ndarray) -> bytes:
        """sensor_msgs/Image, mono8, of an H×W array."""
        pixels = np.ascontiguousarray(pixels, dtype=np.uint8)
        height, width = pixels.shape[:2]
        message = self.types[IMAGE](header=self._header(stamp, frame_id), height=height, width=width, encoding="mono8",
                                    is_bigendian=0, step=width, data=pixels.reshape(-1))
        return self._serialize(message, IMAGE)

    def closure(self, stamp: int, fields: dict) -> tuple[str, bytes]:
        """A confirmed loop closure as JSON in a std_msgs/String (no standard ROS message has its fields)."""
        return CLOSURE_TOPIC, self._serialize(self.types[STRING](data=json.dumps(fields, sort_keys=True)), STRING)

    def markers(self, stamp: int, state: MapState) -> tuple[str, bytes]:
        """The whole experience map as a MarkerArray on MARKERS_TOPIC (`marker_array`)."""
        return MARKERS_TOPIC, self.marker_array(stamp, state)

    def marker_array(self, stamp: int, state: MapState) -> bytes:
        """The whole experience map as a MarkerArray in `map`: one SPHERE_LIST of experiences (in
        id order) and one LINE_LIST per link kind, each replacing its previous version (ADD on
        the same namespace and id). Sizes follow the map's extent, so a corridor and a suburb both show."""
        T = self.types
        ids = sorted(state.experiences)
        points = np.array([state.experiences[i] for i in ids], dtype=float).reshape(-1, 2)
        extent = float(np.ptp(points, axis=0).max()) if len(points) > 1 else 0.0
        size = min(max(extent / 150.0, 0.05), 20.0)
        markers = [self._marker(stamp, "experiences", 7, size, COLOURS["experiences"], points)]
        for kind, namespace in LINK_NAMESPACES.items():
            ends = [(state.experiences[s], state.experiences[t]) for (s, t), k in state.links.items()
                    if k == kind and s in state.experiences and t in state.experiences]
            if ends:
                markers.append(self._marker(stamp, namespace, 5, size / 3, COLOURS[kind], np.array(ends).reshape(-1, 2)))
        return self._serialize(T[MARKER_ARRAY](markers=markers), MARKER_ARRAY)

    def _marker(self, stamp: int, namespace: str, kind: int, size: float, colour, points: np.ndarray):
        T = self.types
        Point = T["geometry_msgs/msg/Point"]
        return T["visualization_msgs/msg/Marker"](
            header=self._header(stamp, MAP_FRAME), ns=namespace, id=0, type=kind, action=0,
            pose=T["geometry_msgs/msg/Pose"](position=Point(x=0.0, y=0.0, z=0.0), orientation=self._quaternion()),
            scale=self._vector(size, size, size), color=T["std_msgs/msg/ColorRGBA"](r=colour[0], g=colour[1], b=colour[2], a=colour[3]),
            lifetime=T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0), frame_locked=False,
            points=[Point(x=float(x), y=float(y), z=0.0) for x, y in points], colors=[], texture_resource="",
            texture=T[COMPRESSED_IMAGE](header=self._header(0, ""), format="", data=np.zeros(0, np.uint8)),
            uv_coordinates=[], text="", mesh_resource="",
            mesh_file=T["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)),
            mesh_use_embedded_materials=False)
