"""ROS bags written with `rosbags` from frames of a gridslam source, for the tests of the bag
source: ROS 1 (.bag) and ROS 2 (sqlite3 or MCAP storage), mono or stereo, raw or compressed
images, with CameraInfo and nav_msgs/Odometry as a robot's driver would record them."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from services.common.geometry import planar_from_camera

FORMATS = ("ros1", "sqlite3", "mcap")
LEFT, RIGHT, ODOM = "/stereo/left/image_raw", "/stereo/right/image_raw", "/robot/odom"


def write_bag(path: Path, frames, *, fmt: str = "mcap", stereo: bool = True, compression: str | None = None,
              encoding: str = "mono8", odometry: bool = True, camera_info: bool = True, left_topic: str = LEFT,
              odom_topic: str = ODOM, right_delays: dict[int, float] | None = None) -> Path:
    """Write `frames` (gridslam Frames) into a bag at `path`; returns the path to open.

    compression None writes sensor_msgs/Image in `encoding` (mono8 from grey frames, or
    rgb8/bgr8/mono16 converted from them; any other name is written as mono8 bytes under that
    name); "png" or "jpeg" writes sensor_msgs/CompressedImage on `<topic>/compressed`. Message
    record times are the frame stamps; `right_delays` (frame index → seconds) stamps some right
    images late."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    ros1 = fmt == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = store.types
    if ros1:
        writer = Writer1(path)
    else:
        writer = Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3)
    image_type = "sensor_msgs/msg/CompressedImage" if compression else "sensor_msgs/msg/Image"
    suffix = "/compressed" if compression else ""
    cameras = [("left", left_topic)] + ([("right", RIGHT)] if stereo else [])
    right_delays = right_delays or {}

    def header(stamp: float, frame_id: str):
        sec = int(math.floor(stamp))
        time = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((stamp - sec) * 1e9)))
        return T["std_msgs/msg/Header"](seq=0, stamp=time, frame_id=frame_id) if ros1 else \
            T["std_msgs/msg/Header"](stamp=time, frame_id=frame_id)

    def serialize(message, msgtype):
        return store.serialize_ros1(message, msgtype) if ros1 else store.serialize_cdr(message, msgtype)

    def image_message(image: np.ndarray, stamp: float, frame_id: str):
        if compression:
            ok, data = cv2.imencode(".png" if compression == "png" else ".jpg", image)
            assert ok
            return T["sensor_msgs/msg/CompressedImage"](header=header(stamp, frame_id), format=compression,
                                                        data=np.frombuffer(data.tobytes(), np.uint8))
        pixels = {"mono8": image, "bgr8": cv2.cvtColor(image, cv2.COLOR_GRAY2BGR),
                  "rgb8": cv2.cvtColor(image, cv2.COLOR_GRAY2RGB),
                  "mono16": image.astype("<u2") * 257}.get(encoding, image) if image.ndim == 2 else image
        data = np.frombuffer(np.ascontiguousarray(pixels).tobytes(), np.uint8)
        height, width = image.shape[:2]
        return T["sensor_msgs/msg/Image"](header=header(stamp, frame_id), height=height, width=width, encoding=encoding,
                                          is_bigendian=0, step=len(data) // height, data=data)

    def info_message(camera, stamp: float, frame_id: str, baseline: float):
        k = np.array([camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1], dtype=float)
        p = np.array([camera.fx, 0, camera.cx, -camera.fx * baseline, 0, camera.fy, camera.cy, 0, 0, 0, 1, 0], dtype=float)
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        matrices = {"D": np.zeros(5), "K": k, "R": np.eye(3).reshape(9), "P": p}
        if not ros1:
            matrices = {name.lower(): value for name, value in matrices.items()}
        return T["sensor_msgs/msg/CameraInfo"](header=header(stamp, frame_id), height=camera.height, width=camera.width,
                                               distortion_model="plumb_bob", **matrices, binning_x=0, binning_y=0, roi=roi)

    def odometry_message(pose: np.ndarray, stamp: float):
        x, y, yaw = planar_from_camera(pose)
        point = T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0)
        rotation = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))
        zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        return T["nav_msgs/msg/Odometry"](
            header=header(stamp, "odom"), child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=T["geometry_msgs/msg/Pose"](position=point, orientation=rotation),
                                                           covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
                                                             covariance=np.zeros(36)))

    writer.open()
    try:
        def connection(topic, msgtype):
            return writer.add_connection(topic, msgtype, typestore=store)

        images = {side: connection(topic + suffix, image_type) for side, topic in cameras}
        infos = {side: connection(topic.rsplit("/", 1)[0] + "/camera_info", "sensor_msgs/msg/CameraInfo")
                 for side, topic in cameras} if camera_info else {}
        odom = connection(odom_topic, "nav_msgs/msg/Odometry") if odometry else None
        for index, frame in enumerate(frames):
            stamp_ns = int(round(frame.stamp * 1e9))
            for side, _ in cameras:
                image = frame.left if side == "left" else frame.right
                stamp = frame.stamp + (right_delays.get(index, 0.0) if side == "right" else 0.0)
                writer.write(images[side], stamp_ns, serialize(image_message(image, stamp, f"camera_{side}"), image_type))
                if side in infos:
                    baseline = frame.camera.baseline if side == "right" else 0.0
                    writer.write(infos[side], stamp_ns, serialize(info_message(frame.camera, frame.stamp, f"camera_{side}",
                                                                               baseline), "sensor_msgs/msg/CameraInfo"))
            if odom is not None:
                writer.write(odom, stamp_ns, serialize(odometry_message(frame.ground_truth, frame.stamp),
                                                       "nav_msgs/msg/Odometry"))
    finally:
        writer.close()
    return path


def image_topic(stereo: bool = False, compression: str | None = None, side: str = "left") -> str:
    return (RIGHT if side == "right" else LEFT) + ("/compressed" if compression else "")


def main() -> None:
    """`python -m tests.bags --source synthetic:0 --preset synthetic --out demo.bag`: a bag of any
    gridslam source, as the tests write them (for the figures of docs/ecosystem.md)."""
    import argparse

    from services.source import open_source

    parser = argparse.ArgumentParser(description=main.__doc__.splitlines()[0])
    parser.add_argument("--source", required=True)
    parser.add_argument("--preset")
    parser.add_argument("--n-frames", type=int)
    parser.add_argument("--out", type=Path, required=True, help="a .bag file (ros1) or a ROS 2 bag folder")
    parser.add_argument("--format", choices=FORMATS, default="mcap")
    parser.add_argument("--compression", choices=["png", "jpeg"])
    parser.add_argument("--mono", action="store_true")
    args = parser.parse_args()
    with open_source(args.source, preset=args.preset, stop=args.n_frames, mono=args.mono) as source:
        write_bag(args.out, source, fmt=args.format, stereo=not args.mono, compression=args.compression)
    print(f"wrote {args.out}: topics {image_topic(compression=args.compression)}"
          + ("" if args.mono else f", {image_topic(compression=args.compression, side='right')}") + f", {ODOM}")


if __name__ == "__main__":
    main()
