"""What a synthetic world renders of a layout other than the corridor ring (campus.py builds
one): wall segments, which texture each shows, the lamps, the look-alike pairs and the
free-space raster; and the sizes every layout shares."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.source.world.route import Route

LAMP_SPACING = 3.0  # metres between ceiling lamps along the centre line
PILLAR_SIZE = 0.3  # metres, square pillars


def in_region(points: np.ndarray, region: tuple[float, float, float, float]) -> np.ndarray:
    """Which of the points (N×2) lie in the region (x0, x1, y0, y1), borders included."""
    x0, x1, y0, y1 = region
    return (points[:, 0] >= x0) & (points[:, 0] <= x1) & (points[:, 1] >= y0) & (points[:, 1] <= y1)


@dataclass(frozen=True)
class Twin:
    """A look-alike pair: everything inside ``region`` (x0, x1, y0, y1; it must hold one
    straight corridor and no junction) is copied to ``region + offset``."""

    region: tuple[float, float, float, float]
    offset: tuple[float, float]

    def moved(self) -> tuple[float, float, float, float]:
        x0, x1, y0, y1 = self.region
        dx, dy = self.offset
        return x0 + dx, x1 + dx, y0 + dy, y1 + dy


RASTER = 0.02  # metres per pixel of the free-space raster the walls are traced from


@dataclass(frozen=True)
class Layout:
    """What the world needs of a layout. Segments are (x0, y0, dx, dy); ``texture_of[k]`` is
    the segment whose texture segment k shows (k itself, or its twin's original);
    ``texture_shift[k]`` where along that segment (metres) segment k's texture starts;
    ``lamp_schedule_of`` likewise for the lamps' on/off schedules."""

    route: Route
    segments: np.ndarray
    texture_of: np.ndarray
    texture_shift: np.ndarray
    lamps: np.ndarray
    lamp_headings: np.ndarray
    lamp_schedule_of: np.ndarray
    twins: tuple[Twin, ...]
    free: np.ndarray            # free-space raster (uint8, 1 inside the corridors)
    origin: tuple[float, float]  # world position of raster pixel (0, 0)

    def is_free(self, x, y) -> np.ndarray:
        """Whether world points lie inside the corridors (not in a wall, pillar or block)."""
        col = np.rint((np.asarray(x) - self.origin[0]) / RASTER).astype(int)
        row = np.rint((np.asarray(y) - self.origin[1]) / RASTER).astype(int)
        inside = (row >= 0) & (row < self.free.shape[0]) & (col >= 0) & (col < self.free.shape[1])
        result = np.zeros(np.shape(col), bool)
        result[inside] = self.free[row[inside], col[inside]] > 0
        return result

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1) of the raster: the floor and ceiling must cover it."""
        height, width = self.free.shape
        return self.origin[0], self.origin[1], self.origin[0] + (width - 1) * RASTER, self.origin[1] + (height - 1) * RASTER
