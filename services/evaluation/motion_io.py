"""Motion-only inputs for the grid-cell integrator: load any supported file into one
`MotionInput` (per-frame increments, stamps, start pose, ground truth when known).

Supported inputs (the format is inferred from the extension, then the content, when not given):
- `csv`: a header line and one row per frame, either
  * body-frame increments `forward,left,yaw` (m, m, rad per frame; yaw counter-clockwise), or
  * world-frame velocities `vx,vy` (m per frame) with an optional absolute `heading` (rad), or
  * the LIBVISO2 ego-motion table of the NuBot sequence (`delta_orientation_rad`,
    `vel_x_relative_m`, `vel_y_relative_m`; ../shared/data/README.md), which is body-frame in
    camera axes: x right, z forward, so forward = vel_y_relative_m, left = -vel_x_relative_m.
  An optional time column (`t`, `time`, `stamp` or `timestamp`, s) gives the stamps;
  otherwise the stamps are the frame index.
- `kitti`: a KITTI pose file (camera convention x right, y down, z forward), flattened onto the
  planar world (x forward, y left, yaw about z up); stamps from a `times.txt` beside the file
  when it has one line per pose, otherwise 10 Hz (KITTI's camera rate).
- `tum`: a TUM trajectory (`stamp tx ty tz qx qy qz qw`), taken as planar (x, y, yaw about z).
- `rat`: a `.npz` with `t` (s) and `pos` (m, N×2), like the ratinabox recordings in
  ../shared/data/rats/ (world-frame: the position series gives the velocities).

Trajectories (kitti, tum, rat) keep every pose as a row: row 0 is the start (zero motion) and
row k the motion from pose k-1 to pose k, so the integrated output has one pose per input
row, in the trajectory's own world frame, and the trajectory is the ground truth.
"""

from __future__ import annotations

import csv
import logging
import math
import zipfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from services.common.errors import DataError
from services.evaluation.trajectory import (
    Trajectory,
    camera_to_planar,
    planar_increments,
    read_kitti,
    read_tum,
)

log = logging.getLogger(__name__)

FORMATS = ("csv", "kitti", "tum", "rat")
BODY_COLUMNS = ("forward", "left", "yaw")
WORLD_COLUMNS = ("vx", "vy")
LIBVISO2_COLUMNS = ("delta_orientation_rad", "vel_x_relative_m", "vel_y_relative_m")
TIME_COLUMNS = ("t", "time", "stamp", "timestamp")
KITTI_FRAME_PERIOD_S = 0.1  # KITTI odometry cameras run at 10 Hz (Geiger et al., CVPR 2012)


class MotionInputError(DataError):
    """A motion input file is missing, unreadable, of an unknown format or malformed."""


@dataclass(frozen=True, eq=False)
class MotionInput:
    """Per-frame motion of one run, ready for an integrator.

    `frame` is "body" (increments (N, 3): forward m, left m, yaw rad per frame) or "world"
    (increments (N, 2): vx, vy in m per frame, with `heading` (N,) rad when the input gives it).
    Body-frame increments follow the integrators' convention (integrator.py, the authors'
    code): the frame first turns by yaw, then moves by (forward, left) in its new body frame.
    `start` is the pose (x, y, heading) before row 0 in the input's world frame.
    `groundtruth` is the true trajectory (N poses) when the input is one.
    `network_rotation` (rad) turns the world frame the integrators run in away from the output
    frame (results are turned back): the network is not rotation invariant (four preferred
    directions, a hexagonal lattice, integer shifts), so this fixes which world inputs it sees.
    """

    path: Path
    format: str
    layout: str
    frame: str
    stamps: np.ndarray
    increments: np.ndarray
    start: tuple[float, float, float] = (0.0, 0.0, 0.0)
    heading: np.ndarray | None = None
    groundtruth: Trajectory | None = None
    network_rotation: float = 0.0

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def step_lengths(self) -> np.ndarray:
        """Distance moved in each frame (N,), m."""
        return np.hypot(self.increments[:, 0], self.increments[:, 1])

    def head(self, n_frames: int | None) -> MotionInput:
        """The first `n_frames` rows (all rows when None or larger than the input)."""
        if n_frames is None or n_frames >= len(self):
            return self
        if n_frames < 1:
            raise MotionInputError(f"{self.path}: --n-frames must be at least 1, got {n_frames}")
        keep = slice(0, n_frames)
        return replace(
            self,
            stamps=self.stamps[keep],
            increments=self.increments[keep],
            heading=None if self.heading is None else self.heading[keep],
            groundtruth=None if self.groundtruth is None else self.groundtruth.select(keep),
        )

    def describe(self) -> str:
        return f"{self.path} ({self.format}/{self.layout}, {self.frame}-frame, {len(self)} frames)"


# --- entry point ----------------------------------------------------------------------------
def load_motion(path, fmt: str | None = None) -> MotionInput:
    """Load a motion input; `fmt` is one of FORMATS, or None to infer it."""
    path = Path(path)
    _check_readable(path)
    fmt = infer_format(path) if fmt is None else fmt.lower()
    if fmt not in FORMATS:
        raise MotionInputError(f"{path}: unknown format '{fmt}' (choose one of {', '.join(FORMATS)})")
    loader = {"csv": load_csv, "kitti": load_kitti, "tum": load_tum, "rat": load_rat}[fmt]
    motion = loader(path)
    log.info("loaded %s", motion.describe())
    return motion


def _check_readable(path: Path) -> None:
    if not path.exists():
        raise MotionInputError(f"{path}: no such file")
    if path.is_dir():
        raise MotionInputError(f"{path}: is a directory, not a motion file")
    try:
        with path.open("rb") as handle:
            head = handle.read(1)
    except OSError as error:
        raise MotionInputError(f"{path}: cannot read ({error.strerror or error})") from None
    if not head:
        raise MotionInputError(f"{path}: file is empty")


def infer_format(path: Path) -> str:
    """The format from the extension (.csv, .tum, .npz), else from the first data line:
    12 numbers are a KITTI pose, 8 a TUM pose, a line with letters a CSV header."""
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return "csv"
    if suffix == ".tum":
        return "tum"
    if suffix == ".npz" or zipfile.is_zipfile(path):
        return "rat"
    line = _first_data_line(path)
    tokens = line.replace(",", " ").split()
    try:
        [float(token) for token in tokens]
    except ValueError:
        if "," in line:
            return "csv"
        raise MotionInputError(
            f"{path}: cannot infer the format from the first line {line[:60]!r} (use --format {'|'.join(FORMATS)})"
        ) from None
    if len(tokens) == 12:
        return "kitti"
    if len(tokens) == 8:
        return "tum"
    raise MotionInputError(
        f"{path}: cannot infer the format: the first line has {len(tokens)} numbers "
        f"(KITTI has 12, TUM 8; use --format {'|'.join(FORMATS)})"
    )


def _read_text(path: Path) -> str:
    try:
        return path.read_text()
    except UnicodeDecodeError:
        raise MotionInputError(f"{path}: not a text file") from None
    except OSError as error:
        raise MotionInputError(f"{path}: cannot read ({error.strerror or error})") from None


def _first_data_line(path: Path) -> str:
    for line in _read_text(path).splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            return line.strip()
    raise MotionInputError(f"{path}: file has no data lines")


# --- CSV ------------------------------------------------------------------------------------
def load_csv(path: Path) -> MotionInput:
    """Body-frame increments, world-frame velocities or the LIBVISO2 table (module docstring)."""
    rows = list(csv.reader(_read_text(path).splitlines()))
    # Skip blank and comment lines, keeping the 1-based line number of each row for messages.
    numbered = [
        (number, row)
        for number, row in enumerate(rows, start=1)
        if "".join(row).strip() and not row[0].lstrip().startswith("#")
    ]
    if not numbered:
        raise MotionInputError(f"{path}: file is empty")
    header_line, header = numbered[0]
    header = [name.strip() for name in header]
    data = numbered[1:]
    layout, columns = _csv_layout(path, header_line, header)
    if not data:
        raise MotionInputError(f"{path}: no data rows after the header")
    time_column = next((name for name in TIME_COLUMNS if name in header), None)
    optional = ["heading"] if layout == "world" and "heading" in header else []
    wanted = list(columns) + optional + ([time_column] if time_column else [])
    index = {name: header.index(name) for name in wanted}
    values = np.empty((len(data), len(wanted)))
    for row_number, (line, row) in enumerate(data):
        if len(row) != len(header):
            raise MotionInputError(f"{path}: line {line}: {len(row)} fields, the header has {len(header)}")
        for j, name in enumerate(wanted):
            token = row[index[name]].strip()
            try:
                value = float(token)
            except ValueError:
                raise MotionInputError(f"{path}: line {line}: column '{name}' is not a number: {token!r}") from None
            if not math.isfinite(value):
                raise MotionInputError(f"{path}: line {line}: column '{name}' is not finite: {token!r}")
            values[row_number, j] = value
    stamps = values[:, wanted.index(time_column)] if time_column else np.arange(len(data), dtype=float)
    if time_column and np.any(np.diff(stamps) < 0):
        bad = int(np.flatnonzero(np.diff(stamps) < 0)[0]) + 1
        raise MotionInputError(f"{path}: line {data[bad][0]}: column '{time_column}' goes back in time")
    if layout == "body":
        return MotionInput(path, "csv", "body", "body", stamps, values[:, :3].copy())
    if layout == "libviso2":
        # Camera axes (x right, z forward; README): forward = z, left = -x. The orientation
        # change asin(-Tt13) is counter-clockwise positive seen from above.
        yaw, right, forward = values[:, 0], values[:, 1], values[:, 2]
        increments = np.column_stack([forward, -right, yaw])
        # The output starts at the origin heading along x (the planar convention). The
        # authors' code ran the network in a world with x = the start's right and y = the
        # start's forward (it rotates camera x/z by the heading), i.e. turned by +90 degrees:
        # running it there feeds the network exactly the world-frame inputs their code computed
        # (../shared/data/seed_reference/nubot_first40_frames.csv).
        return MotionInput(path, "csv", "libviso2", "body", stamps, increments, network_rotation=math.pi / 2)
    heading = values[:, 2].copy() if optional else None
    return MotionInput(path, "csv", "world", "world", stamps, values[:, :2].copy(), heading=heading)


def _csv_layout(path: Path, line: int, header: list[str]) -> tuple[str, tuple[str, ...]]:
    layouts = {"libviso2": LIBVISO2_COLUMNS, "body": BODY_COLUMNS, "world": WORLD_COLUMNS}
    for layout, columns in layouts.items():
        if all(name in header for name in columns):
            return layout, columns
    # Name the missing column of the layout the header comes closest to.
    layout, columns = max(layouts.items(), key=lambda item: sum(name in header for name in item[1]))
    if not any(name in header for name in columns):
        raise MotionInputError(
            f"{path}: line {line}: header {','.join(header)[:80]!r} has none of the expected columns "
            f"(forward,left,yaw or vx,vy[,heading] or {','.join(LIBVISO2_COLUMNS)})"
        )
    missing = next(name for name in columns if name not in header)
    raise MotionInputError(f"{path}: line {line}: missing column '{missing}' (a {layout} CSV needs {','.join(columns)})")


# --- trajectories ---------------------------------------------------------------------------
def load_kitti(path: Path) -> MotionInput:
    """KITTI poses → planar ground truth → body-frame increments."""
    stamps = _kitti_stamps(path)
    traj = camera_to_planar(read_kitti(path, stamps=stamps))
    return motion_from_trajectory(traj, path, "kitti")


def _kitti_stamps(path: Path) -> np.ndarray | None:
    n_poses = sum(1 for line in _read_text(path).splitlines() if line.split("#", 1)[0].strip())
    times = path.with_name("times.txt")
    if times.is_file():
        try:
            stamps = np.loadtxt(times, ndmin=1)
        except ValueError:
            stamps = None
        if stamps is not None and len(stamps) == n_poses:
            return stamps
        log.warning("%s does not hold one stamp per pose of %s; using 10 Hz", times, path)
    return np.arange(n_poses) * KITTI_FRAME_PERIOD_S


def load_tum(path: Path) -> MotionInput:
    """TUM trajectory → planar (x, y, yaw about z) ground truth → body-frame increments."""
    traj = read_tum(path)
    x, y, yaw = traj.planar()
    return motion_from_trajectory(Trajectory.from_planar(traj.stamps, x, y, yaw), path, "tum")


def motion_from_trajectory(traj: Trajectory, path: Path, fmt: str) -> MotionInput:
    """Body-frame increments of a planar trajectory (row 0 zero), starting at its first pose,
    in the integrators' convention (translation in the body frame after the frame's yaw)."""
    if len(traj) < 2:
        raise MotionInputError(f"{path}: needs at least 2 poses, found {len(traj)}")
    # planar_increments expresses step k in the body frame of pose k-1 (T_k = T_{k-1}·Δ_k);
    # the integrators turn first and then move (heading += yaw, then rotate the translation by
    # the new heading, as the authors' code does), so rotate each step by -yaw to match.
    forward_before, left_before, yaw = planar_increments(traj)
    cos_y, sin_y = np.cos(yaw), np.sin(yaw)
    forward = cos_y * forward_before + sin_y * left_before
    left = -sin_y * forward_before + cos_y * left_before
    x, y, heading = traj.planar()
    start = (float(x[0]), float(y[0]), float(heading[0]))
    return MotionInput(path, fmt, "poses", "body", traj.stamps, np.column_stack([forward, left, yaw]), start=start, groundtruth=traj)


def load_rat(path: Path) -> MotionInput:
    """A `.npz` with `t` (s, N) and `pos` (m, N×2): world-frame velocities, ground truth."""
    try:
        with np.load(path, allow_pickle=False) as archive:
            missing = [key for key in ("t", "pos") if key not in archive.files]
            if missing:
                raise MotionInputError(f"{path}: missing key '{missing[0]}' (a rat file holds 't' and 'pos'; found {', '.join(archive.files) or 'none'})")
            t = np.asarray(archive["t"], dtype=float).reshape(-1)
            pos = np.asarray(archive["pos"], dtype=float)
    except MotionInputError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile) as error:
        raise MotionInputError(f"{path}: not a readable .npz ({error})") from None
    if pos.ndim != 2 or pos.shape[1] < 2 or pos.shape[0] != len(t):
        raise MotionInputError(f"{path}: 'pos' has shape {pos.shape}, expected ({len(t)}, 2)")
    if len(t) < 2:
        raise MotionInputError(f"{path}: needs at least 2 samples, found {len(t)}")
    for key, values in (("t", t), ("pos", pos[:, :2])):
        bad = np.flatnonzero(~np.all(np.isfinite(values.reshape(len(t), -1)), axis=1))
        if len(bad):
            raise MotionInputError(f"{path}: key '{key}' sample {int(bad[0])} is not finite")
    if np.any(np.diff(t) <= 0):
        raise MotionInputError(f"{path}: key 't' sample {int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1} does not increase")
    xy = pos[:, :2]
    velocity = np.vstack([[0.0, 0.0], np.diff(xy, axis=0)])
    truth = Trajectory.from_planar(t, xy[:, 0], xy[:, 1], _travel_direction(velocity))
    return MotionInput(path, "rat", "positions", "world", t, velocity, start=(float(xy[0, 0]), float(xy[0, 1]), 0.0), groundtruth=truth)


def _travel_direction(velocity: np.ndarray) -> np.ndarray:
    """Direction of travel per row (rad); a still row keeps the previous direction."""
    angles = np.arctan2(velocity[:, 1], velocity[:, 0])
    moving = np.hypot(velocity[:, 0], velocity[:, 1]) > 0
    last = np.maximum.accumulate(np.where(moving, np.arange(len(angles)), 0))
    return np.where(moving[last], angles[last], 0.0)


# --- noise ----------------------------------------------------------------------------------
def add_noise(motion: MotionInput, noise_trans: float = 0.0, noise_rot_deg: float = 0.0, seed: int = 0) -> MotionInput:
    """Zero-mean Gaussian odometry noise, seeded.

    `noise_trans` is the standard deviation of each translation component as a fraction of
    that frame's step length (0.02 = 2 %); `noise_rot_deg` the standard deviation of the
    per-frame rotation (degrees): the yaw increment for body-frame inputs (so heading error
    accumulates, as in real odometry), the direction of the velocity vector for world-frame ones.
    """
    if noise_trans < 0 or noise_rot_deg < 0:
        raise MotionInputError(f"{motion.path}: noise must be non-negative (trans {noise_trans}, rot {noise_rot_deg})")
    if noise_trans == 0 and noise_rot_deg == 0:
        return motion
    rng = np.random.default_rng(seed)
    n = len(motion)
    step = motion.step_lengths()
    translation = rng.normal(size=(n, 2)) * (noise_trans * step)[:, None]
    rotation = np.deg2rad(noise_rot_deg) * rng.normal(size=n)
    increments = motion.increments.copy()
    if motion.frame == "body":
        increments[:, :2] += translation
        increments[:, 2] += rotation
        heading = motion.heading
    else:
        cos_r, sin_r = np.cos(rotation), np.sin(rotation)
        vx, vy = increments[:, 0].copy(), increments[:, 1].copy()
        increments[:, 0] = cos_r * vx - sin_r * vy + translation[:, 0]
        increments[:, 1] = sin_r * vx + cos_r * vy + translation[:, 1]
        heading = None if motion.heading is None else motion.heading + rotation
    return replace(motion, increments=increments, heading=heading)
