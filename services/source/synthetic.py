"""A synthetic world: a procedural corridor loop rendered on the fly by a pinhole mono or
stereo camera, with exact ground truth and exact odometry.

The scene (docs/sources.md has the picture): a rectangular ring corridor, floor, ceiling
and full-height walls (a 2.5-D world), with square pillars standing against the walls. Every
wall carries its own procedural texture (panels, bricks, posters, doors, shelves, speckle),
the floor carpet tiles and stains, the ceiling tiles and lamps; lighting from the lamps is
baked into the textures, so a place looks the same on every lap. The camera drives the
corridor's centre line (a rectangle with rounded corners, counter-clockwise) at a constant
speed, swaying sideways by a smooth ``wander`` whose phase differs from lap to lap.

Rendering casts one ray per image column against the wall segments (exact hit and depth),
then maps every pixel to a texel: wall pixels by (distance along the walls, height), floor
and ceiling pixels by their world position on the plane; one ``cv2.remap`` per texture atlas
samples them. Textures are pre-filtered at several blur levels (a poor man's anisotropic
mip-map) chosen from each pixel's texel footprint, so distant walls do not alias. A fixed
vignette, a small per-frame exposure change and Gaussian sensor noise make frames look like
a real camera's. Everything derives from the seed: frame k is identical however it is reached.

Conventions: the world is planar, x east, y north, yaw counter-clockwise from x; the camera
looks along the heading, level, ``camera_height`` above the floor. ``Frame.ground_truth`` is
the camera pose in the first selected camera's frame, camera convention (x right, y down,
z forward); ``Frame.odometry`` is the exact body-frame (forward, left, yaw) motion since the
previous selected frame ((0, 0, 0) for the first).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import cv2
import numpy as np

from services.common.errors import ConfigError
from services.source.datasets import IndexedSource
from services.source.frames import Camera, Frame

# Texture resolutions (texels per metre): walls are seen from 1.5 m, floor and ceiling at
# grazing angles from 2 m on, so they need fewer.
WALL_TEXELS_PER_M = 100.0
PLANE_TEXELS_PER_M = 64.0
# The wall texture is one long strip (all walls end to end) folded into rows of this width:
# cv2.remap works on images narrower than 32767 pixels.
STRIP_ROW = 4096
# Blur levels of the pre-filtered textures: level k suits a footprint of about 2**k texels.
BLUR_LEVELS = 4
PAD = 8  # texels between atlas bands, so bilinear sampling never reads the neighbouring band
LAMP_SPACING = 3.0  # metres between ceiling lamps along the centre line
PILLAR_SIZE = 0.3  # metres, square pillars


@dataclass(frozen=True)
class WorldConfig:
    """Settings of the synthetic world; lengths in metres. The camera (image size, focal
    length, stereo baseline) is a separate ``Camera`` (``default_camera``)."""

    seed: int = 0
    length: float = 12.0  # centre line's extent along x (east-west)
    breadth: float = 8.0  # centre line's extent along y (north-south)
    corridor_width: float = 3.0
    wall_height: float = 2.6
    camera_height: float = 1.2
    laps: int = 2
    speed: float = 0.1  # metres per frame along the centre line
    frames_per_lap: int = 0  # 0: route length / speed; otherwise it sets the speed
    fps: float = 10.0  # frame rate for timestamps
    wander: float = 0.05  # amplitude of the sideways sway, metres (phase differs per lap)
    pillar_spacing: float = 4.0  # mean distance between pillars along the walls (0: none)
    noise: float = 2.0  # standard deviation of the sensor noise, grey levels
    exposure_jitter: float = 0.02  # standard deviation of the per-frame exposure gain

    def check(self) -> None:
        """Raise ConfigError naming the first setting that makes no world."""
        half = self.corridor_width / 2
        rules = [
            ("corridor_width", self.corridor_width > 0.6),
            ("length", self.length > self.corridor_width + 0.5),
            ("breadth", self.breadth > self.corridor_width + 0.5),
            ("camera_height", 0 < self.camera_height < self.wall_height),
            ("laps", self.laps >= 1),
            ("speed", self.speed > 0),
            ("frames_per_lap", self.frames_per_lap >= 0),
            ("fps", self.fps > 0),
            ("wander", 0 <= self.wander < half - PILLAR_SIZE - 0.2),
            ("pillar_spacing", self.pillar_spacing == 0 or self.pillar_spacing >= 1.0),
            ("noise", self.noise >= 0),
            ("exposure_jitter", 0 <= self.exposure_jitter < 0.5),
        ]
        for name, ok in rules:
            if not ok:
                raise ConfigError(f"synthetic world: {name} = {getattr(self, name)!r} is out of range")


def default_camera(width: int = 320, height: int = 240, hfov_deg: float = 80.0, baseline: float = 0.12) -> Camera:
    """A pinhole camera with square pixels and a centred principal point; ``baseline`` 0 makes it monocular."""
    f = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
    return Camera(fx=f, fy=f, cx=(width - 1) / 2, cy=(height - 1) / 2, baseline=baseline, width=width, height=height)


# ---------------------------------------------------------------------------------------
# The route: the corridor's centre line, a rectangle with rounded corners (radius = half
# the corridor width), counter-clockwise, starting mid-way along the south side heading east.


class Route:
    """Arc-length parametrised centre line; ``at(s)`` gives position, heading and curvature."""

    def __init__(self, half_x: float, half_y: float, radius: float):
        a, b, r = half_x, half_y, radius
        # (length, curvature) pieces; positions integrate from (0, -b) heading east.
        self.pieces = [
            (a - r, 0.0),
            (math.pi * r / 2, 1 / r),
            (2 * (b - r), 0.0),
            (math.pi * r / 2, 1 / r),
            (2 * (a - r), 0.0),
            (math.pi * r / 2, 1 / r),
            (2 * (b - r), 0.0),
            (math.pi * r / 2, 1 / r),
            (a - r, 0.0),
        ]
        self.starts = []  # (s0, x0, y0, heading0) of each piece
        s, x, y, h = 0.0, 0.0, -b, 0.0
        for length, k in self.pieces:
            self.starts.append((s, x, y, h))
            x, y, h = self._advance(x, y, h, k, length)
            s += length
        self.length = s

    @staticmethod
    def _advance(x: float, y: float, h: float, k: float, d: float) -> tuple[float, float, float]:
        if k == 0:
            return x + d * math.cos(h), y + d * math.sin(h), h
        h1 = h + k * d
        return x + (math.sin(h1) - math.sin(h)) / k, y - (math.cos(h1) - math.cos(h)) / k, h1

    def at(self, s: float) -> tuple[float, float, float, float]:
        """(x, y, heading, curvature) at arc length ``s`` (taken modulo the route length)."""
        s = s % self.length
        for (s0, x0, y0, h0), (length, k) in zip(self.starts, self.pieces):
            if s <= s0 + length:
                x, y, h = self._advance(x0, y0, h0, k, s - s0)
                return x, y, h, k
        raise AssertionError("unreachable: s is within the route")


# ---------------------------------------------------------------------------------------
# Textures


def _blur_levels(texture: np.ndarray, axis: str) -> list[np.ndarray]:
    """Copies of ``texture`` pre-filtered for footprints of 1, 2, 4, 8 texels along ``axis``
    ('x', 'y' or 'xy'): a Gaussian of σ ≈ footprint/2 suppresses what the pixel grid cannot hold."""
    levels = [texture]  # uint8 in, uint8 out: cv2 blurs 8-bit images fastest
    for k in range(1, BLUR_LEVELS):
        sigma = 0.5 * 2**k
        sx = sigma if "x" in axis else 0.01
        sy = sigma if "y" in axis else 0.01
        levels.append(cv2.GaussianBlur(texture, (0, 0), sigmaX=sx, sigmaY=sy, borderType=cv2.BORDER_REFLECT))
    return levels


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> np.ndarray:
    """Zero-mean, unit-ish band-limited noise."""
    noise = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma)
    return noise / (noise.std() + 1e-6)


def _paint_wall(rng: np.random.Generator, width: int, height: int, res: float) -> np.ndarray:
    """A wall strip of ``width``×``height`` texels: panels of varying style, each with
    corners and edges for feature detectors, plus speckle at two scales."""
    wall = np.empty((height, width), np.float32)
    x = 0
    while x < width:
        panel = int(rng.uniform(0.8, 2.5) * res)
        x1 = min(width, x + panel)
        base = rng.uniform(70, 190)
        wall[:, x:x1] = base
        style = rng.integers(5)
        region = wall[:, x:x1]
        w = x1 - x
        if style == 0:  # bricks: staggered rectangles with mortar
            bh, bw = int(rng.uniform(0.07, 0.12) * res), int(rng.uniform(0.2, 0.35) * res)
            for row, top in enumerate(range(0, height, bh)):
                offset = (bw // 2) * (row % 2)
                for left in range(-offset, w, bw):
                    shade = base + rng.uniform(-25, 25)
                    cv2.rectangle(region, (left + 1, top + 1), (left + bw - 2, top + bh - 2), float(shade), -1)
                cv2.line(region, (0, top), (w, top), float(base - 50), 1)
        elif style == 1:  # poster: a framed picture of random blocks at eye height
            top, bottom = int(0.9 * res), int(rng.uniform(1.6, 2.0) * res)
            left, right = int(0.1 * w), int(0.9 * w)
            cv2.rectangle(region, (left - 3, height - bottom - 3), (right + 3, height - top + 3), float(base - 60), -1)
            for _ in range(int(rng.integers(8, 20))):
                px, py = rng.integers(left, max(left + 1, right)), rng.integers(height - bottom, height - top)
                pw, ph = rng.integers(5, 40), rng.integers(5, 40)
                cv2.rectangle(region, (int(px), int(py)), (int(min(px + pw, right)), int(min(py + ph, height - top))), float(rng.uniform(10, 250)), -1)
        elif style == 2:  # door: dark leaf, lighter frame, a handle
            dw = min(w - 4, int(0.9 * res))
            left = (w - dw) // 2
            cv2.rectangle(region, (left - 4, height - int(2.05 * res)), (left + dw + 4, height - 1), float(min(240, base + 50)), -1)
            cv2.rectangle(region, (left, height - int(2.0 * res)), (left + dw, height - 1), float(rng.uniform(30, 80)), -1)
            cv2.circle(region, (left + dw - 10, height - int(1.0 * res)), 4, 220.0, -1)
            for y in (int(0.5 * res), int(1.4 * res)):
                cv2.rectangle(region, (left + 8, height - y - 25), (left + dw - 8, height - y), float(rng.uniform(60, 110)), 2)
        elif style == 3:  # shelves with boxes
            for level in np.arange(0.3, 2.0, rng.uniform(0.35, 0.5)):
                y = height - int(level * res)
                cv2.line(region, (0, y), (w, y), float(base - 70), 3)
                bx = int(rng.integers(0, 10))
                while bx < w - 10:
                    bw, bh = int(rng.integers(8, 30)), int(rng.integers(10, 30))
                    cv2.rectangle(region, (bx, y - bh), (min(w - 1, bx + bw), y - 2), float(rng.uniform(20, 240)), -1)
                    bx += bw + int(rng.integers(2, 12))
        else:  # scattered marks: notices, switches, stickers
            for _ in range(int(rng.integers(6, 16))):
                px, py = int(rng.integers(0, w)), int(rng.integers(0, height))
                size = int(rng.integers(4, 25))
                cv2.rectangle(region, (px, py), (px + size, py + int(size * rng.uniform(0.5, 1.5))), float(rng.uniform(0, 255)), -1)
        cv2.line(wall, (x, 0), (x, height), float(base - 40), 2)  # panel joint
        x = x1
    wall[height - int(0.1 * res):, :] *= 0.5  # skirting board
    wall += 12 * _smooth_noise(rng, wall.shape, 6.0) + 6 * _smooth_noise(rng, wall.shape, 1.0)
    return wall


def _paint_plane(rng: np.random.Generator, shape: tuple[int, int], res: float, tile: float, base: float, spread: float) -> np.ndarray:
    """Floor or ceiling: tiles of ``tile`` metres, each a slightly different shade, grout
    lines between them, stains and fine texture."""
    height, width = shape
    step = int(tile * res)
    shades = rng.uniform(base - spread, base + spread, size=(height // step + 1, width // step + 1)).astype(np.float32)
    plane = cv2.resize(shades, (shades.shape[1] * step, shades.shape[0] * step), interpolation=cv2.INTER_NEAREST)[:height, :width].copy()
    plane[::step, :] -= 35
    plane[:, ::step] -= 35
    for _ in range(int(width * height / res**2 * 0.8)):  # stains, about one per 1.25 m²
        centre = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        axes = (int(rng.integers(2, 12)), int(rng.integers(2, 12)))
        cv2.ellipse(plane, centre, axes, float(rng.uniform(0, 180)), 0, 360, float(rng.uniform(base - 70, base + 40)), -1)
    plane += 8 * _smooth_noise(rng, plane.shape, 4.0) + 5 * _smooth_noise(rng, plane.shape, 1.0)
    return plane


def _lamp_light(points: np.ndarray, lamps: np.ndarray, height_below_lamp: np.ndarray | float) -> np.ndarray:
    """Illumination gain at points ``height_below_lamp`` under the ceiling, from ceiling lamps
    at ``lamps`` (x, y): ambient plus a smooth inverse-square falloff 1/(1 + d²/2 m²)."""
    below2 = np.asarray(height_below_lamp, np.float32) ** 2
    gain = sum(0.9 / (1.0 + (((points - lamp) ** 2).sum(axis=-1) + below2) / 2.0) for lamp in lamps)
    return np.minimum(0.45 + gain, 1.25).astype(np.float32)


# ---------------------------------------------------------------------------------------


class SyntheticWorld(IndexedSource):
    """The synthetic world as a frame source (module docstring). ``camera`` defaults to
    ``default_camera()`` (320×240, 80° field of view, 0.12 m baseline); ``mono=True`` or a zero
    baseline renders the left image only."""

    def __init__(
        self,
        config: WorldConfig = WorldConfig(),
        *,
        camera: Camera | None = None,
        mono: bool = False,
        start: int = 0,
        stop: int | None = None,
        step: int = 1,
        origin: int | None = None,
    ):
        config.check()
        self.config = config
        camera = camera or default_camera()
        if not camera.width or not camera.height:
            raise ConfigError("synthetic world: the camera needs width and height")
        self._stereo = camera.baseline > 0 and not mono
        if not self._stereo:
            camera = dataclasses.replace(camera, baseline=0.0)
        self.route = Route(config.length / 2, config.breadth / 2, config.corridor_width / 2)
        self.frames_per_lap = config.frames_per_lap or max(1, round(self.route.length / config.speed))
        self.speed = self.route.length / self.frames_per_lap  # laps close exactly
        rng = np.random.default_rng(config.seed)
        self._build_walls(rng)
        self._build_textures(rng)
        self._poses = self._route_poses(self.frames_per_lap * config.laps)
        self._prepare_camera(camera)
        self._step = step
        selected = range(len(self._poses))[start:stop:step]
        # Ground truth is relative to `origin` (a source restarted mid-run keeps its run's origin).
        anchor = origin if origin is not None else (selected[0] if selected else None)
        self._anchor = np.linalg.inv(self.camera_matrix(anchor)) if anchor is not None else np.eye(4)
        super().__init__(f"synthetic:{config.seed}", range(len(self._poses)), camera, start, stop, step)

    # --- geometry ------------------------------------------------------------------

    def _build_walls(self, rng: np.random.Generator) -> None:
        """Wall segments (start point, direction vector) of the outer and inner rectangles
        and of the pillars, with each segment's offset into the texture strip."""
        c = self.config
        ox, oy = c.length / 2 + c.corridor_width / 2, c.breadth / 2 + c.corridor_width / 2
        ix, iy = c.length / 2 - c.corridor_width / 2, c.breadth / 2 - c.corridor_width / 2
        segments: list[tuple[float, float, float, float]] = []

        def rectangle(hx: float, hy: float, cx: float = 0.0, cy: float = 0.0) -> None:
            corners = [(cx - hx, cy - hy), (cx + hx, cy - hy), (cx + hx, cy + hy), (cx - hx, cy + hy)]
            for (x0, y0), (x1, y1) in zip(corners, corners[1:] + corners[:1]):
                segments.append((x0, y0, x1 - x0, y1 - y0))

        rectangle(ox, oy)
        rectangle(ix, iy)
        if c.pillar_spacing > 0:
            half = PILLAR_SIZE / 2
            # Pillars stand against both walls of the four straight sides, away from the corners:
            # (centre coordinate across the corridor, side runs along x, half-extent along it).
            faces = []
            for sign in (-1, 1):
                faces += [
                    (sign * (oy - half), True, ix - 0.5),
                    (sign * (iy + half), True, ix - 0.5),
                    (sign * (ox - half), False, iy - 0.5),
                    (sign * (ix + half), False, iy - 0.5),
                ]
            for across, along_x, extent in faces:
                position = -extent + rng.uniform(0, c.pillar_spacing)
                while position < extent:
                    rectangle(half, half, *((position, across) if along_x else (across, position)))
                    position += rng.uniform(0.6, 1.4) * c.pillar_spacing
        self.segments = np.array(segments)  # (N, 4): x0, y0, dx, dy
        lengths = np.hypot(self.segments[:, 2], self.segments[:, 3])
        texels = np.ceil(lengths * WALL_TEXELS_PER_M).astype(int) + PAD
        self._segment_length = lengths
        self._segment_offset = np.concatenate([[0], np.cumsum(texels)[:-1]]).astype(np.float64)
        self._strip_length = int(texels.sum())
        lamps = [self.route.at(s) for s in np.arange(LAMP_SPACING / 2, self.route.length, LAMP_SPACING)]
        self.lamps = np.array([(x, y) for x, y, _, _ in lamps])
        self._lamp_headings = np.array([h for _, _, h, _ in lamps])

    def _route_poses(self, count: int) -> np.ndarray:
        """Planar poses (x, y, yaw) of every frame: the centre line offset sideways by
        w(u) = A sin(2π u / λ), u the distance driven, so laps differ slightly. Heading is the tangent of the offset curve: d/ds (c + w n) =
        (1 − w κ) t + w' n for a centre line c with tangent t, left normal n, curvature κ."""
        amplitude = self.config.wander
        # About 15 m per sway, with a third of a sway left over per lap: each lap's path is
        # shifted by a third of a period (up to √3·A sideways from the previous lap's).
        wavelength = self.route.length / (max(1, round(self.route.length / 15.0)) + 1 / 3)
        poses = np.empty((count, 3))
        for i in range(count):
            u = i * self.speed
            x, y, h, k = self.route.at(u)
            h += 2 * math.pi * (u // self.route.length)  # keep the heading continuous over laps
            w = amplitude * math.sin(2 * math.pi * u / wavelength)
            dw = amplitude * 2 * math.pi / wavelength * math.cos(2 * math.pi * u / wavelength)
            poses[i] = (x - w * math.sin(h), y + w * math.cos(h), h + math.atan2(dw, 1 - w * k))
        return poses

    def planar_pose(self, seq: int) -> tuple[float, float, float]:
        """World pose (x, y, yaw) of frame ``seq``; yaw is continuous (it grows by 2π per lap)."""
        x, y, yaw = self._poses[seq]
        return float(x), float(y), float(yaw)

    def camera_matrix(self, seq: int) -> np.ndarray:
        """4×4 pose of the camera of frame ``seq`` in the world (camera x right, y down, z forward)."""
        x, y, yaw = self._poses[seq]
        c, s = math.cos(yaw), math.sin(yaw)
        pose = np.eye(4)
        pose[:3, :3] = [[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]]  # columns: right, down, forward
        pose[:3, 3] = (x, y, self.config.camera_height)
        return pose

    def odometry(self, previous: int, seq: int) -> tuple[float, float, float]:
        """Exact body-frame motion (forward, left, yaw) from frame ``previous`` to ``seq``."""
        x0, y0, h0 = self._poses[previous]
        x1, y1, h1 = self._poses[seq]
        dx, dy = x1 - x0, y1 - y0
        c, s = math.cos(h0), math.sin(h0)
        return (float(c * dx + s * dy), float(-s * dx + c * dy), float(h1 - h0))

    # --- textures ------------------------------------------------------------------

    def _build_textures(self, rng: np.random.Generator) -> None:
        c = self.config
        res = WALL_TEXELS_PER_M
        wall_texels = int(math.ceil(c.wall_height * res))
        wall = _paint_wall(rng, self._strip_length, wall_texels, res)
        # Light baked per texel: the wall point's world position from its strip coordinate.
        along = np.arange(self._strip_length) + 0.5
        segment = np.searchsorted(self._segment_offset, along, side="right") - 1
        t = np.clip((along - self._segment_offset[segment]) / res / self._segment_length[segment], 0, 1)
        points = self.segments[segment, :2] + t[:, None] * self.segments[segment, 2:]
        heights = c.wall_height - (np.arange(wall_texels) + 0.5) / res  # height above floor of each texel row
        light = _lamp_light(points[None, ::4, :].astype(np.float32), self.lamps.astype(np.float32), (c.wall_height - heights)[:, None])
        wall *= cv2.resize(light, (self._strip_length, wall_texels), interpolation=cv2.INTER_LINEAR)
        wall = np.clip(wall, 0, 255).astype(np.uint8)
        # Fold the strip into rows; every (x-level, y-level) pair of blur gets its own band.
        rows = -(-self._strip_length // STRIP_ROW)
        folded = np.zeros((rows * (wall_texels + PAD), STRIP_ROW), np.uint8)
        for r in range(rows):
            piece = wall[:, r * STRIP_ROW:(r + 1) * STRIP_ROW]
            folded[r * (wall_texels + PAD):r * (wall_texels + PAD) + wall_texels, :piece.shape[1]] = piece
        self._wall_band = rows * (wall_texels + PAD)
        self._wall_rows_texels = wall_texels + PAD
        bands = [level_y for level_x in _blur_levels(folded, "x") for level_y in _blur_levels(level_x, "y")]
        self._wall_atlas = np.concatenate(bands)

        # Floor and ceiling cover the outer rectangle; world (x, y) → texel (col, row).
        res = PLANE_TEXELS_PER_M
        half_x = c.length / 2 + c.corridor_width / 2 + 0.5
        half_y = c.breadth / 2 + c.corridor_width / 2 + 0.5
        self._plane_origin = (-half_x, -half_y)
        shape = (int(2 * half_y * res), int(2 * half_x * res))
        # Light varies slowly: compute it on a grid 4 texels apart and interpolate.
        gx, gy = np.meshgrid((np.arange(0, shape[1], 4) + 2) / res - half_x, (np.arange(0, shape[0], 4) + 2) / res - half_y)
        ground = np.stack([gx, gy], axis=-1).astype(np.float32)

        def lit(plane: np.ndarray, height_below_lamp: float) -> np.ndarray:
            light = _lamp_light(ground, self.lamps.astype(np.float32), height_below_lamp)
            return plane * cv2.resize(light, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)

        floor = lit(_paint_plane(rng, shape, res, 0.5, 115, 20), c.wall_height)
        ceiling = lit(_paint_plane(rng, shape, res, 0.6, 175, 8), 0.6)
        for (lx, ly), heading in zip(self.lamps, self._lamp_headings):  # the lamps: bright panels across the corridor
            col, row = int((lx + half_x) * res), int((ly + half_y) * res)
            long_side, short_side = int(0.6 * res), int(0.15 * res)
            runs_east_west = abs(math.cos(heading)) > abs(math.sin(heading))
            hw, hh = (short_side, long_side) if runs_east_west else (long_side, short_side)
            cv2.rectangle(ceiling, (col - hw - 3, row - hh - 3), (col + hw + 3, row + hh + 3), 90.0, -1)
            cv2.rectangle(ceiling, (col - hw, row - hh), (col + hw, row + hh), 250.0, -1)
        self._plane_band = shape[0] + PAD
        bands = []
        for plane in (floor, ceiling):
            for level in _blur_levels(np.clip(plane, 0, 255).astype(np.uint8), "xy"):
                bands += [level, np.zeros((PAD, shape[1]), np.uint8)]
        self._plane_atlas = np.concatenate(bands)

    # --- rendering -----------------------------------------------------------------

    def _prepare_camera(self, camera: Camera) -> None:
        self._xn = ((np.arange(camera.width) - camera.cx) / camera.fx).astype(np.float64)
        yn = ((np.arange(camera.height) - camera.cy) / camera.fy).astype(np.float32)
        c = self.config
        with np.errstate(divide="ignore"):
            # Depth of the floor (rows below the horizon) or ceiling (above) seen by each row.
            plane_depth = np.where(yn > 0, c.camera_height / yn, (c.camera_height - c.wall_height) / yn)
        self._yn = yn
        self._plane_depth = np.where(np.isfinite(plane_depth), plane_depth, np.float32(1e9)).astype(np.float32)
        self._is_floor = yn > 0
        # Blur level per row for the planes: the footprint along depth, d(depth)/d(row) in texels.
        footprint = np.abs(np.gradient(self._plane_depth)) * PLANE_TEXELS_PER_M
        level = np.clip(np.floor(np.log2(np.maximum(footprint, 1e-6))), 0, BLUR_LEVELS - 1)
        self._plane_row_offset = ((level + np.where(self._is_floor, 0, BLUR_LEVELS)) * self._plane_band).astype(np.float32)
        # A fixed vignette (cos⁴-like falloff of a real lens, mild).
        gx, gy = np.meshgrid(self._xn, yn)
        self._vignette = (1.0 / (1.0 + 0.25 * (gx**2 + gy**2)) ** 2).astype(np.float32)

    def _cast(self, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per image column: depth of the nearest wall, its strip coordinate (texels) and the
        horizontal texel footprint. Ray u is origin + t·(forward + xn·right), so t is depth."""
        forward = np.array([math.cos(yaw), math.sin(yaw)])
        right = np.array([math.sin(yaw), -math.cos(yaw)])
        d = forward[None, :] + self._xn[:, None] * right[None, :]  # (W, 2)
        p, e = self.segments[:, :2], self.segments[:, 2:]
        w = p - np.array([x, y])  # (N, 2)
        denom = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]  # cross(d, e), (W, N)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (w[None, :, 0] * e[None, :, 1] - w[None, :, 1] * e[None, :, 0]) / denom
            s = (w[None, :, 0] * d[:, None, 1] - w[None, :, 1] * d[:, None, 0]) / denom
        hit = (t > 1e-6) & (s >= 0) & (s <= 1)
        t = np.where(hit, t, np.inf)
        nearest = np.argmin(t, axis=1)
        columns = np.arange(len(nearest))
        depth = t[columns, nearest]
        strip = self._segment_offset[nearest] + s[columns, nearest] * self._segment_length[nearest] * WALL_TEXELS_PER_M
        footprint = np.abs(np.gradient(strip))
        footprint[np.abs(np.diff(nearest, prepend=nearest[0])) > 0] = 1.0  # no footprint across an edge
        return depth, strip, footprint

    def render(
        self, x: float, y: float, yaw: float, exposure: float = 1.0, noise: np.random.Generator | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The image (uint8 H×W) and depth map (float32 H×W, metres along the optical axis)
        of a camera at world pose (x, y, yaw); ``exposure`` scales the light, ``noise`` draws
        the sensor noise (none when None)."""
        c = self.config
        depth_col, strip, footprint_x = self._cast(x, y, yaw)
        depth_col = depth_col.astype(np.float32)
        is_plane = self._plane_depth[:, None] < depth_col[None, :]
        depth = np.where(is_plane, self._plane_depth[:, None], depth_col[None, :])

        # Walls: texel row from the height of the wall point seen by each pixel.
        res = WALL_TEXELS_PER_M
        row_in_wall = (c.wall_height - c.camera_height + self._yn[:, None] * depth_col[None, :]) * res
        fold = np.floor(strip / STRIP_ROW)
        level_x = np.clip(np.floor(np.log2(np.maximum(footprint_x, 1e-6))), 0, BLUR_LEVELS - 1)
        level_y = np.clip(np.floor(np.log2(np.maximum(depth_col * res / self.camera.fy, 1e-6))), 0, BLUR_LEVELS - 1)
        band = (level_x * BLUR_LEVELS + level_y) * self._wall_band + fold * self._wall_rows_texels
        wall_map_x = np.broadcast_to((strip - fold * STRIP_ROW).astype(np.float32), depth.shape)
        wall_map_y = (row_in_wall + band[None, :]).astype(np.float32)
        walls = cv2.remap(self._wall_atlas, wall_map_x, wall_map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

        # Floor and ceiling: world position of each pixel's ray on the plane.
        forward_x, forward_y = math.cos(yaw), math.sin(yaw)
        ray_x = (forward_x + self._xn * math.sin(yaw)).astype(np.float32)
        ray_y = (forward_y - self._xn * math.cos(yaw)).astype(np.float32)
        res = PLANE_TEXELS_PER_M
        plane_depth = np.minimum(self._plane_depth, 1e3)[:, None]
        plane_map_x = ((x - self._plane_origin[0]) * res + plane_depth * (ray_x * res)[None, :]).astype(np.float32)
        plane_map_y = ((y - self._plane_origin[1]) * res + plane_depth * (ray_y * res)[None, :] + self._plane_row_offset[:, None]).astype(np.float32)
        planes = cv2.remap(self._plane_atlas, plane_map_x, plane_map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

        image = np.where(is_plane, planes, walls).astype(np.float32) * (self._vignette * np.float32(exposure))
        if noise is not None and c.noise:
            image += noise.standard_normal(image.shape, dtype=np.float32) * np.float32(c.noise)
        return np.clip(image + 0.5, 0, 255).astype(np.uint8), depth

    def depth(self, seq: int) -> np.ndarray:
        """Exact depth map (metres along the optical axis) of frame ``seq``'s left camera."""
        return self.render(*self._poses[seq])[1]

    def _read(self, seq: int) -> Frame:
        x, y, yaw = self._poses[seq]
        # Noise and exposure depend on (seed, seq) only, so a frame is the same however it is reached.
        rng = np.random.default_rng([self.config.seed, seq])
        exposure = 1.0 + float(np.clip(self.config.exposure_jitter * rng.standard_normal(), -0.2, 0.2))
        left, _ = self.render(x, y, yaw, exposure, rng)
        right = None
        if self._stereo:  # the right camera sits `baseline` metres along the camera's x (right)
            b = self.camera.baseline
            right, _ = self.render(x + b * math.sin(yaw), y - b * math.cos(yaw), yaw, exposure, rng)
        previous = seq - self._step
        odometry = self.odometry(previous, seq) if previous >= self._seqs[0] else (0.0, 0.0, 0.0)
        return Frame(
            seq=seq,
            stamp=seq / self.config.fps,
            left=left,
            right=right,
            camera=self.camera,
            ground_truth=self._anchor @ self.camera_matrix(seq),
            odometry=odometry,
        )
