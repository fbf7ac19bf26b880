"""Conversions between the cores' numbers and arrays and the wire messages' fields."""

from __future__ import annotations

import math

import numpy as np

from schemas import Image, Point, Pose, Quaternion
from schemas.base import IMAGE_ENCODINGS
from services.common.errors import DataError

_DTYPES = {"mono8": np.uint8, "bgr8": np.uint8, "rgb8": np.uint8, "mono16": np.uint16, "32FC1": np.float32}


def image_to_msg(array: np.ndarray, encoding: str | None = None) -> Image:
    """sensor_msgs/Image from an H×W (grey) or H×W×3 (BGR) array."""
    array = np.ascontiguousarray(array)
    if encoding is None:
        if array.dtype == np.uint8:
            encoding = "mono8" if array.ndim == 2 else "bgr8"
        elif array.dtype == np.uint16:
            encoding = "mono16"
        else:
            encoding, array = "32FC1", array.astype(np.float32)
    height, width = array.shape[:2]
    return Image(height=height, width=width, encoding=encoding, step=width * IMAGE_ENCODINGS[encoding],
                 data=array.tobytes())


def image_from_msg(image: Image) -> np.ndarray:
    """The pixels of a sensor_msgs/Image as an array (a read-only view of the bytes)."""
    dtype = np.dtype(_DTYPES[image.encoding]).newbyteorder(">" if image.is_bigendian else "<")
    channels = 3 if image.encoding in ("bgr8", "rgb8") else 1
    rows = np.frombuffer(image.data, dtype=np.uint8).reshape(image.height, image.step)
    pixels = rows[:, : image.width * IMAGE_ENCODINGS[image.encoding]].copy().view(dtype)
    if pixels.dtype.kind == "f" and not np.isfinite(pixels).all():
        # The schema forbids NaN and infinity in every field; pixels are bytes to it, so check here.
        raise DataError(f"{image.encoding} image of {image.width}×{image.height} has NaN or infinite pixels")
    return pixels.reshape(image.height, image.width, channels) if channels > 1 else pixels.reshape(image.height, image.width)


def planar_pose(x: float, y: float, heading: float) -> Pose:
    """A planar pose (yaw about z) as geometry_msgs/Pose."""
    return Pose(position=Point(x=x, y=y, z=0.0),
                orientation=Quaternion(x=0.0, y=0.0, z=math.sin(heading / 2), w=math.cos(heading / 2)))


def pose_to_matrix(pose: Pose) -> np.ndarray:
    """4×4 homogeneous transform of a pose."""
    q = pose.orientation
    x, y, z, w = q.x, q.y, q.z, q.w
    matrix = np.eye(4)
    matrix[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    matrix[:3, 3] = [pose.position.x, pose.position.y, pose.position.z]
    return matrix


def matrix_to_pose(matrix: np.ndarray) -> Pose:
    """geometry_msgs/Pose of a 4×4 homogeneous transform (rotation part must be orthonormal)."""
    r = np.asarray(matrix, dtype=float)[:3, :3]
    # Shepperd's method: pick the largest of the four diagonal combinations for stability.
    trace = np.trace(r)
    candidates = [trace, r[0, 0], r[1, 1], r[2, 2]]
    i = int(np.argmax(candidates))
    if i == 0:
        s = 2 * math.sqrt(1 + trace)
        q = ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4)
    elif i == 1:
        s = 2 * math.sqrt(1 + r[0, 0] - r[1, 1] - r[2, 2])
        q = (s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s)
    elif i == 2:
        s = 2 * math.sqrt(1 + r[1, 1] - r[0, 0] - r[2, 2])
        q = ((r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s)
    else:
        s = 2 * math.sqrt(1 + r[2, 2] - r[0, 0] - r[1, 1])
        q = ((r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s)
    norm = math.sqrt(sum(c * c for c in q))
    t = np.asarray(matrix, dtype=float)[:3, 3]
    return Pose(position=Point(x=t[0], y=t[1], z=t[2]),
                orientation=Quaternion(x=q[0] / norm, y=q[1] / norm, z=q[2] / norm, w=q[3] / norm))


def heading_of(pose: Pose) -> float:
    """Yaw about z of a pose's orientation."""
    q = pose.orientation
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
