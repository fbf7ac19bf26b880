"""Trajectories: one type, the TUM and KITTI file formats, and planar conventions.

Conventions used everywhere in gridslam:
- A `Trajectory` holds N poses of the body in a world frame: `stamps` (s), `positions`
  (m) and unit `quaternions` in x, y, z, w order (the TUM order, also scipy's).
- Planar world: x forward (at the start), y left, z up; yaw about z, counter-clockwise
  positive, in radians. The pipeline (ego-motion increments, grid cells, experience map)
  works in this frame.
- Camera frame (KITTI ground truth): x right, y down, z forward. `camera_to_planar` and
  `planar_to_camera` convert between the two.
- Ego-motion increments are body-frame planar motions between consecutive frames:
  forward (m), left (m), yaw (rad), one per frame, the first one being the motion into
  frame 0 (zero for a trajectory's own increments).

File formats:
- TUM RGB-D: one pose per line, `stamp tx ty tz qx qy qz qw`, `#` starts a comment
  (Sturm et al., IROS 2012, and the TUM benchmark's file format page).
- KITTI odometry: one pose per line, 12 numbers, the row-major 3×4 matrix [R|t] of the
  pose (Geiger et al., CVPR 2012, devkit readme); no timestamps.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.common.errors import DataError
from services.common.geometry import wrap

log = logging.getLogger(__name__)

TUM_COLUMNS = ("stamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
KITTI_COLUMNS = ("r11", "r12", "r13", "tx", "r21", "r22", "r23", "ty", "r31", "r32", "r33", "tz")

# Planar world axes expressed in camera axes (rows): x_planar = z_cam (forward),
# y_planar = -x_cam (left), z_planar = -y_cam (up). A proper rotation (det +1).
PLANAR_FROM_CAMERA = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


class TrajectoryFormatError(DataError):
    """A trajectory file or array is malformed (the message names the file and line)."""


@dataclass(frozen=True, eq=False)
class Trajectory:
    """N timestamped poses: stamps (N,) s, positions (N, 3) m, quaternions (N, 4) x, y, z, w."""

    stamps: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray

    def __post_init__(self) -> None:
        stamps = np.asarray(self.stamps, dtype=float).reshape(-1)
        positions = np.asarray(self.positions, dtype=float)
        quaternions = np.asarray(self.quaternions, dtype=float)
        n = stamps.shape[0]
        if positions.shape != (n, 3):
            raise TrajectoryFormatError(f"trajectory: positions have shape {positions.shape}, expected ({n}, 3)")
        if quaternions.shape != (n, 4):
            raise TrajectoryFormatError(f"trajectory: quaternions have shape {quaternions.shape}, expected ({n}, 4)")
        for name, values in (("stamps", stamps), ("positions", positions), ("quaternions", quaternions)):
            if not np.all(np.isfinite(values)):
                first = int(np.argwhere(~np.isfinite(values.reshape(n, -1)))[0, 0])
                raise TrajectoryFormatError(f"trajectory: {name} of pose {first} is not finite")
        norms = np.linalg.norm(quaternions, axis=1)
        if n and np.min(norms) < 1e-9:
            raise TrajectoryFormatError(f"trajectory: quaternion of pose {int(np.argmin(norms))} has zero length")
        quaternions = quaternions / norms[:, None] if n else quaternions
        for name, values in (("stamps", stamps), ("positions", positions), ("quaternions", quaternions)):
            values.flags.writeable = False
            object.__setattr__(self, name, values)

    # --- construction -------------------------------------------------------------------
    @classmethod
    def from_planar(cls, stamps, x, y, yaw) -> Trajectory:
        """Poses on the ground plane (z = 0) with heading `yaw` (rad, about z up)."""
        x, y, yaw = (np.asarray(v, dtype=float).reshape(-1) for v in (x, y, yaw))
        stamps = np.asarray(stamps, dtype=float).reshape(-1)
        if not (len(stamps) == len(x) == len(y) == len(yaw)):
            raise TrajectoryFormatError(
                f"trajectory: planar arrays differ in length (stamps {len(stamps)}, x {len(x)}, y {len(y)}, yaw {len(yaw)})"
            )
        zeros = np.zeros_like(x)
        quaternions = np.stack([zeros, zeros, np.sin(yaw / 2.0), np.cos(yaw / 2.0)], axis=1)
        return cls(stamps, np.stack([x, y, zeros], axis=1), quaternions)

    @classmethod
    def from_matrices(cls, stamps, matrices) -> Trajectory:
        """Poses from homogeneous transforms (N, 4, 4) or (N, 3, 4) of body in world."""
        matrices = np.asarray(matrices, dtype=float)
        stamps = np.asarray(stamps, dtype=float).reshape(-1)
        if matrices.ndim != 3 or matrices.shape[1:] not in ((4, 4), (3, 4)):
            raise TrajectoryFormatError(f"trajectory: matrices have shape {matrices.shape}, expected (N, 4, 4)")
        if matrices.shape[0] != stamps.shape[0]:
            raise TrajectoryFormatError(f"trajectory: {matrices.shape[0]} matrices but {stamps.shape[0]} stamps")
        if not np.all(np.isfinite(matrices)):
            first = int(np.argwhere(~np.isfinite(matrices.reshape(len(matrices), -1)))[0, 0])
            raise TrajectoryFormatError(f"trajectory: matrix of pose {first} is not finite")
        if len(matrices) == 0:
            return cls(stamps, np.zeros((0, 3)), np.zeros((0, 4)))
        return cls(stamps, matrices[:, :3, 3], _quaternions_from_rotations(matrices[:, :3, :3]))

    # --- views --------------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def rotations(self) -> np.ndarray:
        """Rotation matrices (N, 3, 3), body to world."""
        x, y, z, w = self.quaternions.T   # unit length (the constructor normalises them)
        return np.stack([
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ], axis=-2)

    def matrices(self) -> np.ndarray:
        """Homogeneous transforms (N, 4, 4), body to world."""
        matrices = np.zeros((len(self), 4, 4))
        matrices[:, :3, :3] = self.rotations()
        matrices[:, :3, 3] = self.positions
        matrices[:, 3, 3] = 1.0
        return matrices

    def planar(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, y, yaw): position on the ground plane and heading of the body's x axis about z."""
        rotations = self.rotations()
        yaw = np.arctan2(rotations[:, 1, 0], rotations[:, 0, 0])
        return self.positions[:, 0].copy(), self.positions[:, 1].copy(), yaw

    def cumulative_distances(self) -> np.ndarray:
        """Distance travelled from pose 0 to each pose (N,), m, along the 3D polyline."""
        steps = np.linalg.norm(np.diff(self.positions, axis=0), axis=1)
        return np.concatenate([[0.0], np.cumsum(steps)])

    def path_length(self) -> float:
        """Total distance travelled, m."""
        return float(self.cumulative_distances()[-1]) if len(self) else 0.0

    def select(self, indices) -> Trajectory:
        """The poses at `indices` (a slice, an index array or a boolean mask)."""
        return Trajectory(self.stamps[indices], self.positions[indices], self.quaternions[indices])

    def __repr__(self) -> str:
        return f"Trajectory({len(self)} poses, {self.path_length():.3f} m)"


def _quaternions_from_rotations(rotations: np.ndarray) -> np.ndarray:
    """Unit quaternions (N, 4) x, y, z, w of rotation matrices (N, 3, 3), by Shepperd's method:
    for each matrix, from the largest of its trace and diagonal entries, so that the divisor is
    never small. A matrix a little off orthonormal (rounded in a text file) gives the normalised
    quaternion of a rotation within that error of it."""
    r = rotations
    trace = r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2]
    largest = np.argmax(np.stack([trace, r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]], axis=1), axis=1)
    q = np.empty((len(r), 4))
    for k in range(4):   # k = 0: w is largest; k = 1, 2, 3: x, y or z is
        m = r[largest == k]
        if k == 0:
            q[largest == k] = np.stack([m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1],
                                        1 + m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]], axis=1)
            continue
        i = k - 1
        j, l = (i + 1) % 3, (i + 2) % 3
        part = np.empty((len(m), 4))
        part[:, i] = 1 + m[:, i, i] - m[:, j, j] - m[:, l, l]
        part[:, j] = m[:, j, i] + m[:, i, j]
        part[:, l] = m[:, l, i] + m[:, i, l]
        part[:, 3] = m[:, l, j] - m[:, j, l]
        q[largest == k] = part
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# --- conventions ----------------------------------------------------------------------------
def _conjugate(traj: Trajectory, change: np.ndarray) -> Trajectory:
    """Express both the world and the body frame in new axes: T' = C T Cᵀ."""
    matrices = traj.matrices()
    full = np.eye(4)
    full[:3, :3] = change
    return Trajectory.from_matrices(traj.stamps, full @ matrices @ full.T)


def camera_to_planar(traj: Trajectory, keep_height: bool = False) -> Trajectory:
    """Camera-convention poses (x right, y down, z forward; KITTI) to the planar world
    (x forward, y left, z up; yaw counter-clockwise about z).

    By default the result is flattened onto the ground plane (z = 0, roll and pitch dropped),
    so that it compares directly with planar estimates; `keep_height=True` keeps the full
    6-DoF pose, only re-expressed in the planar axes.
    """
    converted = _conjugate(traj, PLANAR_FROM_CAMERA)
    if keep_height:
        return converted
    x, y, yaw = converted.planar()
    return Trajectory.from_planar(traj.stamps, x, y, yaw)


def planar_to_camera(traj: Trajectory) -> Trajectory:
    """Planar-world poses (x forward, y left, z up) to the camera convention (x right,
    y down, z forward), the convention of KITTI pose files. Inverse of
    `camera_to_planar(..., keep_height=True)`."""
    return _conjugate(traj, PLANAR_FROM_CAMERA.T)


# --- increments (dead reckoning) ------------------------------------------------------------
def planar_increments(traj: Trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-frame body-frame planar motions (forward m, left m, yaw rad), each (N,).

    Increment k is the SE(2) motion from pose k-1 to pose k expressed in the body frame of
    pose k-1 (T_k = T_{k-1} · Δ_k); increment 0 is zero. `integrate_increments` inverts it.
    """
    x, y, heading = traj.planar()
    n = len(traj)
    forward, left, yaw = np.zeros(n), np.zeros(n), np.zeros(n)
    if n > 1:
        dx, dy = np.diff(x), np.diff(y)
        cos_h, sin_h = np.cos(heading[:-1]), np.sin(heading[:-1])
        forward[1:] = cos_h * dx + sin_h * dy
        left[1:] = -sin_h * dx + cos_h * dy
        yaw[1:] = wrap(np.diff(heading))
    return forward, left, yaw


def integrate_increments(forward, left, yaw, stamps=None, x0: float = 0.0, y0: float = 0.0, heading0: float = 0.0) -> Trajectory:
    """Dead reckoning: compose body-frame increments (forward, left, yaw), one per frame,
    starting from the pose (x0, y0, heading0). Pose k = pose k-1 ∘ Δ_k, with pose -1 the
    start pose, so a zero first increment puts frame 0 at the start pose.

    `stamps` defaults to the frame index. The position step uses the heading before the
    increment's own yaw (exact SE(2) composition, as `planar_increments` defines it).
    """
    forward, left, yaw = (np.asarray(v, dtype=float).reshape(-1) for v in (forward, left, yaw))
    n = len(forward)
    if not (len(left) == n and len(yaw) == n):
        raise DataError(f"increments differ in length (forward {n}, left {len(left)}, yaw {len(yaw)})")
    stamps = np.arange(n, dtype=float) if stamps is None else np.asarray(stamps, dtype=float).reshape(-1)
    if len(stamps) != n:
        raise DataError(f"{n} increments but {len(stamps)} stamps")
    heading_after = heading0 + np.cumsum(yaw)
    heading_before = np.concatenate([[heading0], heading_after[:-1]])
    x = x0 + np.cumsum(np.cos(heading_before) * forward - np.sin(heading_before) * left)
    y = y0 + np.cumsum(np.sin(heading_before) * forward + np.cos(heading_before) * left)
    return Trajectory.from_planar(stamps, x, y, wrap(heading_after))


# --- files ----------------------------------------------------------------------------------
def _read_rows(path: Path, columns: tuple[str, ...], what: str) -> list[tuple[int, list[float]]]:
    """Parse whitespace-separated numbers, one pose per line; blank and `#` lines skipped."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise TrajectoryFormatError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as error:
        raise TrajectoryFormatError(f"{path}: cannot read ({error})") from None
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        content = line.split("#", 1)[0].replace(",", " ").split()
        if not content:
            continue
        if len(content) != len(columns):
            raise TrajectoryFormatError(
                f"{path}: line {number}: expected {len(columns)} numbers ({what}), found {len(content)}"
            )
        values = []
        for column, token in zip(columns, content):
            try:
                value = float(token)
            except ValueError:
                raise TrajectoryFormatError(f"{path}: line {number}: column '{column}' is not a number: {token!r}") from None
            if not math.isfinite(value):
                raise TrajectoryFormatError(f"{path}: line {number}: column '{column}' is not finite: {token!r}")
            values.append(value)
        rows.append((number, values))
    if not rows:
        raise TrajectoryFormatError(f"{path}: no poses (empty file)")
    return rows


def read_tum(path) -> Trajectory:
    """Read a TUM trajectory file (`stamp tx ty tz qx qy qz qw` per line)."""
    rows = _read_rows(Path(path), TUM_COLUMNS, "stamp tx ty tz qx qy qz qw")
    for number, values in rows:
        if math.sqrt(sum(v * v for v in values[4:])) < 1e-9:
            raise TrajectoryFormatError(f"{path}: line {number}: quaternion has zero length")
    data = np.array([values for _, values in rows])
    log.debug("read %d poses from %s", len(data), path)
    return Trajectory(data[:, 0], data[:, 1:4], data[:, 4:8])


def read_kitti(path, stamps=None) -> Trajectory:
    """Read a KITTI pose file (12 numbers per line, row-major 3×4 [R|t]).

    KITTI pose files carry no time; `stamps` gives them (e.g. from the sequence's
    times.txt), otherwise the frame index is used.
    """
    rows = _read_rows(Path(path), KITTI_COLUMNS, "row-major 3x4 [R|t]")
    matrices = np.array([values for _, values in rows]).reshape(-1, 3, 4)
    # A rotation block far from orthonormal is a malformed line, not rounding in the file.
    rotations = matrices[:, :, :3]
    defect = np.abs(rotations @ np.transpose(rotations, (0, 2, 1)) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((defect > 1e-2) | (np.linalg.det(rotations) < 0))
    if len(bad):
        raise TrajectoryFormatError(f"{path}: line {rows[bad[0]][0]}: the 3x3 block is not a rotation matrix")
    if stamps is None:
        stamps = np.arange(len(matrices), dtype=float)
    stamps = np.asarray(stamps, dtype=float).reshape(-1)
    if len(stamps) != len(matrices):
        raise TrajectoryFormatError(f"{path}: {len(matrices)} poses but {len(stamps)} stamps given")
    log.debug("read %d poses from %s", len(matrices), path)
    return Trajectory.from_matrices(stamps, matrices)


def _format_number(value: float) -> str:
    # repr is the shortest string that reads back to the same double: full precision.
    return repr(float(value))


def _write_lines(path: Path, lines: list[str]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(line + "\n" for line in lines))
    return path


def write_tum(path, traj: Trajectory) -> Path:
    """Write a TUM trajectory file at full precision (a `#` header line names the columns)."""
    data = np.column_stack([traj.stamps, traj.positions, traj.quaternions])
    lines = ["# " + " ".join(TUM_COLUMNS)] + [" ".join(_format_number(v) for v in row) for row in data]
    return _write_lines(path, lines)


def write_kitti(path, traj: Trajectory) -> Path:
    """Write a KITTI pose file at full precision (no header: KITTI tools take none).

    The poses are written as they are; for KITTI tools that plot x against z, convert a
    planar trajectory with `planar_to_camera` first.
    """
    rows = traj.matrices()[:, :3, :].reshape(len(traj), 12)
    return _write_lines(path, [" ".join(_format_number(v) for v in row) for row in rows])
