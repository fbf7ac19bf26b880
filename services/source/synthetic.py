"""A synthetic world: a procedural corridor loop rendered on the fly by a pinhole mono or
stereo camera, with exact ground truth and exact odometry. (``layout = "campus"`` swaps the
ring below for a network of corridor loops, campus.py; the renderer is the same.)

The scene (docs/sources.md has the picture): a rectangular ring corridor, floor, ceiling
and full-height walls (a 2.5-D world), with square pillars standing against the walls. Every
wall carries its own procedural texture (panels, bricks, posters, doors, shelves, speckle),
the floor carpet tiles and stains, the ceiling tiles and lamps; lighting from the lamps is
baked into the textures, so a place looks the same on every lap (unless ``lamps_off`` or
``light_variation`` make it change over time: then it is computed per pixel at render time,
``_light``). The camera drives the corridor's centre line (a rectangle with rounded corners,
counter-clockwise) at a constant speed (``max_turn_deg`` slows it in turns), swaying sideways
by a smooth ``wander`` whose phase differs from lap to lap.

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
from services.common.frames import Camera, Frame
from services.source.world.campus import campus_layout
from services.source.world.layout import LAMP_SPACING, PILLAR_SIZE
from services.source.world.route import Route
from services.source.world.textures import (
    BLUR_LEVELS, LARGE_PLANE_TEXELS_PER_M, LARGE_STRIP_ROW, LARGE_WALL_TEXELS_PER_M, PAD, PLANE_TEXELS_PER_M, STRIP_ROW,
    WALL_TEXELS_PER_M, blur_levels, lamp_light, paint_plane, paint_wall,
)

LAYOUTS = ("corridor", "campus")
# Worlds with more wall segments than this cast each ray against the segments near the camera
# first, and against all only where those give no hit close enough to be sure (exact either way).
CULL_SEGMENTS = 256
CULL_RADIUS = 12.0
# Lighting computed at render time (lamps switching, a changing level): on a grid of every
# LIGHT_STEP-th pixel, interpolated (light varies slowly); a lamp's light fades to zero at
# LIGHT_RADIUS metres so that only the lamps near what the camera sees count.
LIGHT_STEP = 4
LIGHT_RADIUS = 12.0
SPEED_RAMP = 3.0  # metres to speed up from standstill to full speed (max_turn_deg > 0)


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
    layout: str = "corridor"  # "corridor": the ring above; "campus": a network of loops (campus.py)
    max_turn_deg: float = 0.0  # 0: constant speed; else the speed drops in turns to turn at most this per frame
    lamps_off: float = 0.0  # fraction of the time each lamp is off (it fades out and in on its own schedule)
    light_variation: float = 0.0  # amplitude of a slow change of the overall light level (0.2: ±20 %)
    light_period: float = 300.0  # seconds: mean period of the lamps' schedules and of the light level

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
            ("layout", self.layout in LAYOUTS),
            ("max_turn_deg", 0 <= self.max_turn_deg <= 45),
            ("lamps_off", 0 <= self.lamps_off < 1),
            ("light_variation", 0 <= self.light_variation < 0.5),
            ("light_period", self.light_period > 0),
        ]
        if self.layout == "campus":  # the campus's corridors run 8 m apart or more
            rules.append(("corridor_width", self.corridor_width <= 5.0))
        for name, ok in rules:
            if not ok:
                raise ConfigError(f"synthetic world: {name} = {getattr(self, name)!r} is out of range")


def default_camera(width: int = 320, height: int = 240, hfov_deg: float = 80.0, baseline: float = 0.12) -> Camera:
    """A pinhole camera with square pixels and a centred principal point; ``baseline`` 0 makes it monocular."""
    f = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
    return Camera(fx=f, fy=f, cx=(width - 1) / 2, cy=(height - 1) / 2, baseline=baseline, width=width, height=height)


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
        rng = np.random.default_rng(config.seed)
        self.layout = None  # the campus's Layout (campus.py); None for the corridor ring
        if config.layout == "corridor":
            self._wall_res, self._plane_res, self._strip_row = WALL_TEXELS_PER_M, PLANE_TEXELS_PER_M, STRIP_ROW
            self.route = Route(config.length / 2, config.breadth / 2, config.corridor_width / 2)
            self._build_walls(rng)
        else:
            self._wall_res, self._plane_res, self._strip_row = LARGE_WALL_TEXELS_PER_M, LARGE_PLANE_TEXELS_PER_M, LARGE_STRIP_ROW
            self.layout = campus_layout(config.corridor_width, config.pillar_spacing, rng)
            self.route = self.layout.route
            self._use_layout(self.layout)
        self._speed_profile()
        self._dynamic_light = config.lamps_off > 0 or config.light_variation > 0
        self._lamp_schedule()
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
        self._texture_of = np.arange(len(self.segments))  # every wall shows its own texture
        lengths = np.hypot(self.segments[:, 2], self.segments[:, 3])
        texels = np.ceil(lengths * WALL_TEXELS_PER_M).astype(int) + PAD
        self._segment_length = lengths
        self._segment_offset = np.concatenate([[0], np.cumsum(texels)[:-1]]).astype(np.float64)
        self._strip_length = int(texels.sum())
        lamps = [self.route.at(s) for s in np.arange(LAMP_SPACING / 2, self.route.length, LAMP_SPACING)]
        self.lamps = np.array([(x, y) for x, y, _, _ in lamps])
        self._lamp_headings = np.array([h for _, _, h, _ in lamps])

    def _use_layout(self, layout) -> None:
        """Walls and lamps of a layout (campus.py); a look-alike's walls share its original's texture."""
        self.segments = layout.segments
        lengths = np.hypot(self.segments[:, 2], self.segments[:, 3])
        owned = layout.texture_of == np.arange(len(lengths))
        texels = np.where(owned, np.ceil(lengths * self._wall_res).astype(int) + PAD, 0)
        self._segment_length = lengths
        self._texture_of = layout.texture_of
        own_offset = np.concatenate([[0], np.cumsum(texels)[:-1]]).astype(np.float64)
        self._segment_offset = own_offset[layout.texture_of] + layout.texture_shift * self._wall_res
        self._strip_length = int(texels.sum())
        self.lamps = layout.lamps
        self._lamp_headings = layout.lamp_headings

    def _speed_profile(self) -> None:
        """Frames per lap, the top speed, and (when the speed varies) every frame's distance
        along a lap. With ``max_turn_deg`` the speed limit is max_turn / curvature, reached by
        ramps of constant acceleration (SPEED_RAMP metres from standstill to full speed); the
        route's start lies on a straight, at full speed. Either way a lap closes exactly."""
        c = self.config
        length = self.route.length
        self._lap_distances = None
        if not c.max_turn_deg:
            self.frames_per_lap = c.frames_per_lap or max(1, round(length / c.speed))
            self.speed = length / self.frames_per_lap
            return
        s = np.linspace(0.0, length, int(math.ceil(length / 0.01)) + 1)
        curvature = np.abs(self.route.curvatures(s))
        limit2 = np.minimum(c.speed, math.radians(c.max_turn_deg) / np.maximum(curvature, 1e-12)) ** 2
        # v² may grow or shrink by 2·a per metre: v²(i) = min over j of limit²(j) + 2a·|s_i − s_j|.
        climb = 2 * (c.speed**2 / (2 * SPEED_RAMP)) * (s[1] - s[0])
        index = np.arange(len(s))
        ahead = np.minimum.accumulate(limit2 - climb * index) + climb * index
        behind = (np.minimum.accumulate((limit2 + climb * index)[::-1]))[::-1] - climb * index
        speed = np.sqrt(np.minimum(ahead, behind))
        time = np.concatenate([[0.0], np.cumsum(np.diff(s) / ((speed[1:] + speed[:-1]) / 2))])  # in frames
        self.frames_per_lap = c.frames_per_lap or max(1, round(time[-1]))
        scale = time[-1] / self.frames_per_lap
        self.speed = c.speed * scale
        self._lap_distances = np.interp(np.arange(self.frames_per_lap) * scale, time, s)

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
            if self._lap_distances is None:
                u = i * self.speed
            else:
                u = (i // self.frames_per_lap) * self.route.length + self._lap_distances[i % self.frames_per_lap]
            x, y, h, k = self.route.at(u)
            h += self.route.lap_turn * (u // self.route.length)  # keep the heading continuous over laps
            w = amplitude * math.sin(2 * math.pi * u / wavelength)
            dw = amplitude * 2 * math.pi / wavelength * math.cos(2 * math.pi * u / wavelength)
            poses[i] = (x - w * math.sin(h), y + w * math.cos(h), h + math.atan2(dw, 1 - w * k))
        return poses

    def distance(self, seq: int) -> float:
        """Distance along the route (metres, growing over laps) of frame ``seq``'s centre-line point."""
        if self._lap_distances is None:
            return seq * self.speed
        lap, index = divmod(seq, self.frames_per_lap)
        return lap * self.route.length + float(self._lap_distances[index])

    @property
    def poses(self) -> np.ndarray:
        """World poses (x, y, continuous yaw) of every frame of the run, selected or not (a copy)."""
        return self._poses.copy()

    def planar_pose(self, seq: int) -> tuple[float, float, float]:
        """World pose (x, y, yaw) of frame ``seq``; yaw is continuous (it grows by the route's whole turns per lap)."""
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
        """Wall strip and floor and ceiling planes, pre-filtered, in two atlases. Light from
        the lamps is baked into them unless it changes at render time (``_dynamic_light``)."""
        c = self.config
        res = self._wall_res
        wall_texels = int(math.ceil(c.wall_height * res))
        wall = paint_wall(rng, self._strip_length, wall_texels, res)
        lamps = self.lamps.astype(np.float32)
        if not self._dynamic_light:
            # Light baked per texel: the wall point's world position from its strip coordinate
            # (a look-alike's walls show their original's texture, light included).
            owners = np.flatnonzero(self._texture_of == np.arange(len(self.segments)))
            along = np.arange(self._strip_length) + 0.5
            segment = owners[np.searchsorted(self._segment_offset[owners], along, side="right") - 1]
            t = np.clip((along - self._segment_offset[segment]) / res / self._segment_length[segment], 0, 1)
            points = self.segments[segment, :2] + t[:, None] * self.segments[segment, 2:]
            heights = c.wall_height - (np.arange(wall_texels) + 0.5) / res  # height above floor of each texel row
            light = lamp_light(points[None, ::4, :].astype(np.float32), lamps, (c.wall_height - heights)[:, None])
            wall *= cv2.resize(light, (self._strip_length, wall_texels), interpolation=cv2.INTER_LINEAR)
        wall = np.clip(wall, 0, 255).astype(np.uint8)
        # Fold the strip into rows; every (x-level, y-level) pair of blur gets its own band.
        rows = -(-self._strip_length // self._strip_row)
        # (The corridor keeps its fixed row width; a large strip's rows are as wide as it needs.)
        row_width = self._strip_row if self.layout is None else -(-self._strip_length // rows)
        self._strip_row = row_width
        folded = np.zeros((rows * (wall_texels + PAD), row_width), np.uint8)
        for r in range(rows):
            piece = wall[:, r * row_width:(r + 1) * row_width]
            folded[r * (wall_texels + PAD):r * (wall_texels + PAD) + wall_texels, :piece.shape[1]] = piece
        self._wall_band = rows * (wall_texels + PAD)
        self._wall_rows_texels = wall_texels + PAD
        # Filled band by band: a large world's atlas is too big to hold twice.
        self._wall_atlas = np.empty((BLUR_LEVELS**2 * self._wall_band, row_width), np.uint8)
        for i, level_x in enumerate(blur_levels(folded, "x")):
            for j, level_y in enumerate(blur_levels(level_x, "y")):
                self._wall_atlas[(i * BLUR_LEVELS + j) * self._wall_band:(i * BLUR_LEVELS + j + 1) * self._wall_band] = level_y

        # Floor and ceiling cover the world's extent; world (x, y) → texel (col, row).
        res = self._plane_res
        if self.layout is None:  # the corridor ring: its outer rectangle
            half_x = c.length / 2 + c.corridor_width / 2 + 0.5
            half_y = c.breadth / 2 + c.corridor_width / 2 + 0.5
            origin_x, origin_y = -half_x, -half_y
            shape = (int(2 * half_y * res), int(2 * half_x * res))
        else:
            x0, y0, x1, y1 = self.layout.bounds
            origin_x, origin_y = x0 - 0.5, y0 - 0.5
            shape = (int((y1 - y0 + 1.0) * res), int((x1 - x0 + 1.0) * res))
        self._plane_origin = (origin_x, origin_y)
        # Light varies slowly: compute it on a grid 4 texels apart and interpolate.
        gx, gy = np.meshgrid((np.arange(0, shape[1], 4) + 2) / res + origin_x, (np.arange(0, shape[0], 4) + 2) / res + origin_y)
        ground = np.stack([gx, gy], axis=-1).astype(np.float32)

        def lit(plane: np.ndarray, height_below_lamp: float) -> np.ndarray:
            if self._dynamic_light:
                return plane
            light = lamp_light(ground, lamps, height_below_lamp)
            return plane * cv2.resize(light, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)

        floor = lit(paint_plane(rng, shape, res, 0.5, 115, 20), c.wall_height)
        ceiling = lit(paint_plane(rng, shape, res, 0.6, 175, 8), 0.6)
        for (lx, ly), heading in zip(self.lamps, self._lamp_headings):  # the lamps: bright panels across the corridor
            col, row = int((lx - origin_x) * res), int((ly - origin_y) * res)
            long_side, short_side = int(0.6 * res), int(0.15 * res)
            runs_east_west = abs(math.cos(heading)) > abs(math.sin(heading))
            hw, hh = (short_side, long_side) if runs_east_west else (long_side, short_side)
            cv2.rectangle(ceiling, (col - hw - 3, row - hh - 3), (col + hw + 3, row + hh + 3), 90.0, -1)
            cv2.rectangle(ceiling, (col - hw, row - hh), (col + hw, row + hh), 250.0, -1)
        for twin in self.layout.twins if self.layout is not None else ():  # look-alikes: the same floor and ceiling
            rx0, rx1, ry0, ry1 = twin.region
            c0, c1 = round((rx0 - origin_x) * res), round((rx1 - origin_x) * res)
            r0, r1 = round((ry0 - origin_y) * res), round((ry1 - origin_y) * res)
            dx, dy = round(twin.offset[0] * res), round(twin.offset[1] * res)
            for plane in (floor, ceiling):
                plane[r0 + dy:r1 + dy, c0 + dx:c1 + dx] = plane[r0:r1, c0:c1]
        self._plane_band = shape[0] + PAD
        bands = []
        for plane in (floor, ceiling):
            for level in blur_levels(np.clip(plane, 0, 255).astype(np.uint8), "xy"):
                bands += [level, np.zeros((PAD, shape[1]), np.uint8)]
        self._plane_atlas = np.concatenate(bands)

    # --- lighting ------------------------------------------------------------------

    def _lamp_schedule(self) -> None:
        """Each lamp's period and phase (a look-alike's lamps follow their original's), and the
        phase of the overall level, from a generator of their own (textures stay as they were)."""
        if not self._dynamic_light:
            return
        c = self.config
        schedule_of = self.layout.lamp_schedule_of if self.layout is not None else np.arange(len(self.lamps))
        rng = np.random.default_rng([c.seed, 1])
        owners = int(schedule_of.max()) + 1
        self._lamp_period = (c.light_period * rng.uniform(0.6, 1.4, owners))[schedule_of]
        self._lamp_phase = rng.uniform(0, 2 * math.pi, owners)[schedule_of]
        self._level_phase = float(rng.uniform(0, 2 * math.pi))

    def lighting(self, time: float | None) -> tuple[float, np.ndarray]:
        """The overall light level and every lamp's intensity (0 off … 1 on) at ``time``
        seconds; None: level 1, every lamp on. A lamp is off a fraction ``lamps_off`` of the
        time: its intensity follows clip((sin(2πt/P + φ) − s₀)/0.5, 0, 1), s₀ = sin(π(f − ½)),
        so it fades over a tenth or so of its period P (0.6–1.4 × light_period)."""
        c = self.config
        on = np.ones(len(self.lamps), np.float32)
        if time is None or not self._dynamic_light:
            return 1.0, on
        level = 1.0 + c.light_variation * math.sin(2 * math.pi * time / (1.7 * c.light_period) + self._level_phase)
        if c.lamps_off > 0:
            threshold = math.sin(math.pi * (c.lamps_off - 0.5))
            wave = np.sin(2 * math.pi * time / self._lamp_period + self._lamp_phase)
            on = np.clip((wave - threshold) / 0.5, 0.0, 1.0).astype(np.float32)
        return level, on

    def _light(self, x: float, y: float, yaw: float, depth: np.ndarray, time: float | None) -> np.ndarray:
        """Light (gain) at every pixel: the lamps' light at the world point each pixel sees, as
        the baked light's formula (lamp_light) with every lamp's intensity and the level,
        computed every LIGHT_STEP pixels and interpolated."""
        c = self.config
        level, on = self.lighting(time)
        rows, cols = self._light_rows, self._light_cols
        d = depth[np.ix_(rows, cols)].astype(np.float32)
        xn, yn = self._xn[cols].astype(np.float32), self._yn[rows]
        cos, sin = np.float32(math.cos(yaw)), np.float32(math.sin(yaw))
        px = np.float32(x) + d * (cos + xn * sin)[None, :]
        py = np.float32(y) + d * (sin - xn * cos)[None, :]
        below2 = np.maximum((c.wall_height - c.camera_height + yn[:, None] * d) ** 2, np.float32(0.36))
        near = ((self.lamps[:, 0] > px.min() - LIGHT_RADIUS) & (self.lamps[:, 0] < px.max() + LIGHT_RADIUS)
                & (self.lamps[:, 1] > py.min() - LIGHT_RADIUS) & (self.lamps[:, 1] < py.max() + LIGHT_RADIUS) & (on > 0))
        gain = np.zeros_like(d)
        for (lx, ly), intensity in zip(self.lamps[near].astype(np.float32), on[near]):
            d2 = (px - lx) ** 2 + (py - ly) ** 2
            taper = np.maximum(1 - d2 / np.float32(LIGHT_RADIUS**2), 0) ** 2  # no light beyond LIGHT_RADIUS
            gain += (np.float32(0.9) * intensity) * taper / (1 + (d2 + below2) / 2)
        light = np.float32(level) * np.minimum(np.float32(0.45) + gain, np.float32(1.25))
        return cv2.resize(light, (depth.shape[1], depth.shape[0]), interpolation=cv2.INTER_LINEAR)

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
        footprint = np.abs(np.gradient(self._plane_depth)) * self._plane_res
        level = np.clip(np.floor(np.log2(np.maximum(footprint, 1e-6))), 0, BLUR_LEVELS - 1)
        self._plane_row_offset = ((level + np.where(self._is_floor, 0, BLUR_LEVELS)) * self._plane_band).astype(np.float32)
        # A fixed vignette (cos⁴-like falloff of a real lens, mild).
        gx, gy = np.meshgrid(self._xn, yn)
        self._vignette = (1.0 / (1.0 + 0.25 * (gx**2 + gy**2)) ** 2).astype(np.float32)
        self._light_rows = np.arange(LIGHT_STEP // 2, camera.height, LIGHT_STEP)
        self._light_cols = np.arange(LIGHT_STEP // 2, camera.width, LIGHT_STEP)

    def _cast(self, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per image column: depth of the nearest wall, its strip coordinate (texels) and the
        horizontal texel footprint. Ray u is origin + t·(forward + xn·right), so t is depth.
        A world of many walls casts against the walls within CULL_RADIUS first: a hit closer
        than that is the nearest of all; the other rays are cast against every wall."""
        forward = np.array([math.cos(yaw), math.sin(yaw)])
        right = np.array([math.sin(yaw), -math.cos(yaw)])
        d = forward[None, :] + self._xn[:, None] * right[None, :]  # (W, 2)
        if len(self.segments) <= CULL_SEGMENTS:
            depth, along, nearest = self._hits(d, x, y)
        else:
            near = np.flatnonzero(self._segment_distance(x, y) <= CULL_RADIUS)
            if len(near):
                depth, along, nearest = self._hits(d, x, y, near)
            else:
                depth, along, nearest = np.full(len(d), np.inf), np.zeros(len(d)), np.zeros(len(d), int)
            far = ~(depth * np.hypot(d[:, 0], d[:, 1]) <= CULL_RADIUS)
            if far.any():
                depth[far], along[far], nearest[far] = self._hits(d[far], x, y)
        strip = self._segment_offset[nearest] + along * self._segment_length[nearest] * self._wall_res
        footprint = np.abs(np.gradient(strip))
        footprint[np.abs(np.diff(nearest, prepend=nearest[0])) > 0] = 1.0  # no footprint across an edge
        return depth, strip, footprint

    def _hits(self, d: np.ndarray, x: float, y: float, index: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For rays ``d`` from (x, y): depth of the nearest of the walls ``index`` (default all),
        where along it (0…1) the ray hits, and which wall it is."""
        segments = self.segments if index is None else self.segments[index]
        p, e = segments[:, :2], segments[:, 2:]
        w = p - np.array([x, y])  # (N, 2)
        denom = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]  # cross(d, e), (W, N)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (w[None, :, 0] * e[None, :, 1] - w[None, :, 1] * e[None, :, 0]) / denom
            s = (w[None, :, 0] * d[:, None, 1] - w[None, :, 1] * d[:, None, 0]) / denom
        hit = (t > 1e-6) & (s >= 0) & (s <= 1)
        t = np.where(hit, t, np.inf)
        nearest = np.argmin(t, axis=1)
        columns = np.arange(len(nearest))
        return t[columns, nearest], s[columns, nearest], nearest if index is None else index[nearest]

    def _segment_distance(self, x: float, y: float) -> np.ndarray:
        """Distance from (x, y) to every wall segment."""
        p, e = self.segments[:, :2], self.segments[:, 2:]
        offset = np.array([x, y]) - p
        u = np.clip((offset * e).sum(axis=1) / (e * e).sum(axis=1), 0, 1)
        return np.hypot(*(offset - u[:, None] * e).T)

    def render(
        self, x: float, y: float, yaw: float, exposure: float = 1.0, noise: np.random.Generator | None = None,
        time: float | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The image (uint8 H×W) and depth map (float32 H×W, metres along the optical axis)
        of a camera at world pose (x, y, yaw); ``exposure`` scales the light, ``noise`` draws
        the sensor noise (none when None), ``time`` (seconds) sets the lamps and the light
        level when the lighting changes (None: every lamp on, level 1)."""
        c = self.config
        depth_col, strip, footprint_x = self._cast(x, y, yaw)
        depth_col = depth_col.astype(np.float32)
        is_plane = self._plane_depth[:, None] < depth_col[None, :]
        depth = np.where(is_plane, self._plane_depth[:, None], depth_col[None, :])

        # Walls: texel row from the height of the wall point seen by each pixel.
        res = self._wall_res
        row_in_wall = (c.wall_height - c.camera_height + self._yn[:, None] * depth_col[None, :]) * res
        fold = np.floor(strip / self._strip_row)
        level_x = np.clip(np.floor(np.log2(np.maximum(footprint_x, 1e-6))), 0, BLUR_LEVELS - 1)
        level_y = np.clip(np.floor(np.log2(np.maximum(depth_col * res / self.camera.fy, 1e-6))), 0, BLUR_LEVELS - 1)
        band = (level_x * BLUR_LEVELS + level_y) * self._wall_band + fold * self._wall_rows_texels
        wall_map_x = np.broadcast_to((strip - fold * self._strip_row).astype(np.float32), depth.shape)
        wall_map_y = (row_in_wall + band[None, :]).astype(np.float32)
        walls = cv2.remap(self._wall_atlas, wall_map_x, wall_map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

        # Floor and ceiling: world position of each pixel's ray on the plane.
        forward_x, forward_y = math.cos(yaw), math.sin(yaw)
        ray_x = (forward_x + self._xn * math.sin(yaw)).astype(np.float32)
        ray_y = (forward_y - self._xn * math.cos(yaw)).astype(np.float32)
        res = self._plane_res
        plane_depth = np.minimum(self._plane_depth, 1e3)[:, None]
        plane_map_x = ((x - self._plane_origin[0]) * res + plane_depth * (ray_x * res)[None, :]).astype(np.float32)
        plane_map_y = ((y - self._plane_origin[1]) * res + plane_depth * (ray_y * res)[None, :] + self._plane_row_offset[:, None]).astype(np.float32)
        planes = cv2.remap(self._plane_atlas, plane_map_x, plane_map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

        image = np.where(is_plane, planes, walls).astype(np.float32) * (self._vignette * np.float32(exposure))
        if self._dynamic_light:
            image *= self._light(x, y, yaw, depth, time)
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
        time = seq / self.config.fps
        left, _ = self.render(x, y, yaw, exposure, rng, time)
        right = None
        if self._stereo:  # the right camera sits `baseline` metres along the camera's x (right)
            b = self.camera.baseline
            right, _ = self.render(x + b * math.sin(yaw), y - b * math.cos(yaw), yaw, exposure, rng, time)
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
