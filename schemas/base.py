"""Shared building blocks of every wire message. Layouts mirror ROS 2
(std_msgs/Header, builtin_interfaces/Time, geometry_msgs, sensor_msgs/Image) so that a
bridge to ROS is a field-by-field copy."""

from __future__ import annotations

from typing import Annotated, ClassVar

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, model_validator

SCHEMA_VERSION = 1

# Bytes per pixel of the image encodings we put on the wire (sensor_msgs/image_encodings names).
IMAGE_ENCODINGS: dict[str, int] = {"mono8": 1, "bgr8": 3, "rgb8": 3, "mono16": 2, "32FC1": 4}


class Model(BaseModel):
    """Base of every schema: immutable, no unknown fields, no NaN or infinity anywhere."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class Message(Model):
    """Base of every top-level message; `KIND` names it on the wire (Zenoh encoding suffix)."""

    KIND: ClassVar[str]
    schema_version: int = Field(
        SCHEMA_VERSION, ge=1, le=SCHEMA_VERSION, description="Version of this message's schema; bumped only by an incompatible change."
    )

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        cls.KIND = cls.__name__


class Time(Model):
    """builtin_interfaces/Time: seconds and nanoseconds since the source's epoch."""

    sec: int = Field(description="Whole seconds of the source timestamp.")
    nanosec: int = Field(ge=0, lt=1_000_000_000, description="Nanoseconds past `sec`, 0 to 999999999.")

    @classmethod
    def from_seconds(cls, seconds: float) -> Time:
        sec = int(seconds // 1)
        return cls(sec=sec, nanosec=min(int(round((seconds - sec) * 1e9)), 999_999_999))

    def to_seconds(self) -> float:
        return self.sec + self.nanosec * 1e-9


class Header(Model):
    """std_msgs/Header plus the frame index and the robot, carried by every message."""

    seq: int = Field(ge=0, description="Index of the camera frame this message derives from; consecutive frames of a stream differ by `stride`, so gaps are detectable.")
    stride: int = Field(1, ge=1, description="How far seq advances from one frame of the stream to the next: 1, or n for a replay that takes every n-th frame of its source (a jump of n is then no gap).")
    stamp: Time = Field(description="Timestamp of the source frame (not of publication).")
    frame_id: str = Field("", description="Coordinate frame the data is expressed in, e.g. 'camera', 'odom', 'map'.")
    robot: str = Field("robot0", description="Robot name; the same as the <robot> chunk of the key expression.")


class Vector3(Model):
    """geometry_msgs/Vector3."""

    x: float = Field(0.0, description="x component.")
    y: float = Field(0.0, description="y component.")
    z: float = Field(0.0, description="z component.")


class Point(Vector3):
    """geometry_msgs/Point: a position in metres."""


class Quaternion(Model):
    """geometry_msgs/Quaternion, Hamilton convention, (x, y, z, w)."""

    x: float = Field(0.0, description="x (imaginary i) component.")
    y: float = Field(0.0, description="y (imaginary j) component.")
    z: float = Field(0.0, description="z (imaginary k) component.")
    w: float = Field(1.0, description="w (real) component.")

    @model_validator(mode="after")
    def _unit(self) -> Quaternion:
        norm2 = self.x**2 + self.y**2 + self.z**2 + self.w**2
        if abs(norm2 - 1.0) > 1e-3:
            raise ValueError(f"quaternion is not unit length (squared norm {norm2:.6g})")
        return self


class Pose(Model):
    """geometry_msgs/Pose: position and orientation."""

    position: Point = Field(default_factory=Point, description="Position in metres.")
    orientation: Quaternion = Field(default_factory=Quaternion, description="Orientation as a unit quaternion.")


class Twist(Model):
    """geometry_msgs/Twist: linear and angular velocity."""

    linear: Vector3 = Field(default_factory=Vector3, description="Linear velocity, metres per second.")
    angular: Vector3 = Field(default_factory=Vector3, description="Angular velocity, radians per second.")


class Image(Model):
    """sensor_msgs/Image: raw pixels as bytes, never nested lists."""

    height: int = Field(ge=1, le=16384, description="Rows.")
    width: int = Field(ge=1, le=16384, description="Columns.")
    encoding: str = Field(description=f"Pixel encoding, one of {sorted(IMAGE_ENCODINGS)}.")
    is_bigendian: bool = Field(False, description="Byte order of multi-byte pixels.")
    step: int = Field(ge=1, description="Bytes per row, at least width × bytes per pixel.")
    data: bytes = Field(description="Row-major pixel bytes, exactly step × height of them.")

    @model_validator(mode="after")
    def _consistent(self) -> Image:
        if self.encoding not in IMAGE_ENCODINGS:
            raise ValueError(f"unknown image encoding {self.encoding!r}; expected one of {sorted(IMAGE_ENCODINGS)}")
        row = self.width * IMAGE_ENCODINGS[self.encoding]
        if self.step < row:
            raise ValueError(f"step {self.step} is smaller than width × bytes per pixel = {row}")
        if len(self.data) != self.step * self.height:
            raise ValueError(f"image data has {len(self.data)} bytes, expected step × height = {self.step * self.height}")
        return self


def _check_covariance(values: list[float]) -> list[float]:
    m = [values[0:3], values[3:6], values[6:9]]
    if any(m[i][i] < 0 for i in range(3)):
        raise ValueError("covariance has a negative variance on its diagonal")
    for i, j in ((0, 1), (0, 2), (1, 2)):
        if abs(m[i][j] - m[j][i]) > 1e-9 * (1.0 + abs(m[i][j])):
            raise ValueError(f"covariance is not symmetric (element {i},{j} {m[i][j]!r} vs {j},{i} {m[j][i]!r})")
    return values


# A 3×3 covariance of a planar (forward, left, yaw) quantity, row-major: symmetric, non-negative variances.
PlanarCovariance = Annotated[list[float], Field(min_length=9, max_length=9), AfterValidator(_check_covariance)]


def covariance_field(what: str):
    return Field(None, description=f"Covariance of {what} as (forward m, left m, yaw rad), 3×3 row-major; absent when unknown.")


class PlanarIncrement(Model):
    """Body-frame planar motion over one frame: x forward, y left, yaw counter-clockwise."""

    forward: float = Field(description="Distance moved forward, metres per frame.")
    left: float = Field(description="Distance moved to the left, metres per frame.")
    yaw: float = Field(description="Heading change, radians per frame, counter-clockwise positive.")
