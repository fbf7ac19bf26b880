"""A textured box room rendered by an exact pinhole camera at any pose: images with known
motion for the estimators' unit tests and benchmark (a pure rotation, a pure translation,
a stereo pair), independent of the source service's synthetic world.

Every pixel's ray is intersected with the six planes of the room (floor, ceiling, four
walls); the nearest hit is textured from a seeded multi-scale noise image (blobs at several
sizes, so there are corners at every pyramid level) by one cv2.remap per plane.
Conventions: camera frame x right, y down, z forward; a pose is camera-to-room (4×4).
"""

from __future__ import annotations


import cv2
import numpy as np

from services.common.geometry import invert_transform, transform_from_increment
from services.common.frames import Camera, Frame

TEXELS_PER_M = 160.0
TEXTURE_SIZE = 1024


def pinhole(width: int, height: int, fov_deg: float = 70.0, baseline: float = 0.12) -> Camera:
    fx = (width / 2.0) / np.tan(np.radians(fov_deg) / 2.0)
    return Camera(fx, fx, (width - 1) / 2.0, (height - 1) / 2.0, baseline, width, height)


class BoxRoom:
    """A room x ∈ [−half_width, half_width], y ∈ [ceiling, floor] (y down), z ∈ [−half_depth,
    half_depth], around a camera starting at the origin ``camera_height`` above the floor."""

    def __init__(self, seed: int = 0, half_width: float = 3.0, half_depth: float = 8.0, camera_height: float = 1.2, ceiling: float = 1.6):
        self.half_width, self.half_depth = half_width, half_depth
        self.floor, self.ceiling = camera_height, -ceiling
        rng = np.random.default_rng(seed)
        self.textures = [_texture(rng) for _ in range(6)]

    def render(self, camera: Camera, pose: np.ndarray, noise: float = 0.0, seed: int = 0) -> np.ndarray:
        """The uint8 grey image seen by ``camera`` at ``pose`` (camera-to-room)."""
        width, height = camera.width, camera.height
        u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        rays = np.stack(((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)), axis=-1)
        rays = rays @ pose[:3, :3].T
        origin = pose[:3, 3]
        # (axis, plane position, texture coordinates' axes)
        planes = [
            (1, self.floor, (0, 2)),
            (1, self.ceiling, (0, 2)),
            (0, -self.half_width, (2, 1)),
            (0, self.half_width, (2, 1)),
            (2, self.half_depth, (0, 1)),
            (2, -self.half_depth, (0, 1)),
        ]
        best = np.full((height, width), np.inf)
        image = np.zeros((height, width), np.float32)
        for texture, (axis, position, (a, b)) in zip(self.textures, planes):
            with np.errstate(divide="ignore", invalid="ignore"):
                distance = (position - origin[axis]) / rays[..., axis]
            visible = (distance > 1e-6) & (distance < best)
            if not visible.any():
                continue
            hit_a = origin[a] + distance * rays[..., a]
            hit_b = origin[b] + distance * rays[..., b]
            map_x = (hit_a * TEXELS_PER_M).astype(np.float32)
            map_y = (hit_b * TEXELS_PER_M).astype(np.float32)
            sampled = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            image[visible] = sampled[visible]
            best[visible] = distance[visible]
        if noise > 0:
            image += np.random.default_rng(seed).normal(0.0, noise, image.shape).astype(np.float32)
        return np.clip(image, 0, 255).astype(np.uint8)

    def frame(self, seq: int, camera: Camera, pose: np.ndarray, stereo: bool = False, **extra) -> Frame:
        left = self.render(camera, pose, noise=1.0, seed=seq)
        right = None
        if stereo:
            offset = np.eye(4)
            offset[0, 3] = camera.baseline
            right = self.render(camera, pose @ offset, noise=1.0, seed=10_000 + seq)
        return Frame(seq, 0.1 * seq, left, right, camera, pose, **extra)


def _texture(rng: np.random.Generator) -> np.ndarray:
    """Periodic multi-scale noise, 0..255 float32: white noise low-passed in the Fourier
    domain (so it tiles) by Gaussians of several widths, each scaled to unit deviation."""
    spectrum = np.fft.rfft2(rng.normal(0.0, 1.0, (TEXTURE_SIZE, TEXTURE_SIZE)))
    fy = np.fft.fftfreq(TEXTURE_SIZE)[:, None]
    fx = np.fft.rfftfreq(TEXTURE_SIZE)[None, :]
    radius2 = fx**2 + fy**2
    # A Gaussian blur of width sigma leaves white noise a deviation of 1 / (2·sqrt(pi)·sigma).
    gain = sum(
        weight * 2.0 * np.sqrt(np.pi) * sigma * np.exp(-2.0 * np.pi**2 * sigma**2 * radius2)
        for sigma, weight in ((1.5, 0.6), (4.0, 1.0), (12.0, 1.0), (40.0, 0.6))
    )
    texture = np.fft.irfft2(spectrum * gain, s=(TEXTURE_SIZE, TEXTURE_SIZE))
    texture -= texture.min()
    return (255.0 * texture / texture.max()).astype(np.float32)


def motion_pose(forward: float = 0.0, left: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    """The camera's motion (pose of the new camera in the old camera's frame) for a planar
    increment; pose_new = pose_old @ motion_pose(...)."""
    return invert_transform(transform_from_increment(forward, left, yaw))


def sequence(
    increments: list[tuple[float, float, float]],
    camera: Camera,
    *,
    stereo: bool = False,
    with_odometry: bool = False,
    seed: int = 0,
    room: BoxRoom | None = None,
) -> list[Frame]:
    """Frames along a path: frame 0 at the origin, then one frame per planar increment."""
    room = room or BoxRoom(seed)
    pose = np.eye(4)
    frames = [room.frame(0, camera, pose, stereo, odometry=(0.0, 0.0, 0.0) if with_odometry else None)]
    for k, increment in enumerate(increments, start=1):
        pose = pose @ motion_pose(*increment)
        frames.append(room.frame(k, camera, pose, stereo, odometry=increment if with_odometry else None))
    return frames
