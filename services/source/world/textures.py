"""A synthetic world's textures: walls painted as panels of several styles (bricks, posters,
doors, shelves, marks), floor and ceiling as tiles with stains, each pre-filtered at several
blur levels (a poor man's anisotropic mip-map: level k suits a footprint of about 2**k
texels), and the lamps' light baked into them (``lamp_light``)."""

from __future__ import annotations

import cv2
import numpy as np

# Texture resolutions (texels per metre): walls are seen from 1.5 m, floor and ceiling at
# grazing angles from 2 m on, so they need fewer.
WALL_TEXELS_PER_M = 100.0
PLANE_TEXELS_PER_M = 64.0
# The wall texture is one long strip (all walls end to end) folded into rows of this width:
# cv2.remap works on images narrower than 32767 pixels.
STRIP_ROW = 4096
# The campus has ten times the walls and thirty times the floor: coarser textures keep its
# atlases near 200 MB (docs/sources.md) and inside cv2.remap's 32767-pixel limit.
LARGE_WALL_TEXELS_PER_M = 64.0
LARGE_PLANE_TEXELS_PER_M = 32.0
LARGE_STRIP_ROW = 16384
# Blur levels of the pre-filtered textures: level k suits a footprint of about 2**k texels.
BLUR_LEVELS = 4
PAD = 8  # texels between atlas bands, so bilinear sampling never reads the neighbouring band


def blur_levels(texture: np.ndarray, axis: str) -> list[np.ndarray]:
    """Copies of ``texture`` pre-filtered for footprints of 1, 2, 4, 8 texels along ``axis``
    ('x', 'y' or 'xy'): a Gaussian of σ ≈ footprint/2 suppresses what the pixel grid cannot hold."""
    levels = [texture]  # uint8 in, uint8 out: cv2 blurs 8-bit images fastest
    for k in range(1, BLUR_LEVELS):
        sigma = 0.5 * 2**k
        sx = sigma if "x" in axis else 0.01
        sy = sigma if "y" in axis else 0.01
        levels.append(cv2.GaussianBlur(texture, (0, 0), sigmaX=sx, sigmaY=sy, borderType=cv2.BORDER_REFLECT))
    return levels


def smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> np.ndarray:
    """Zero-mean, unit-ish band-limited noise."""
    noise = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma)
    return noise / (noise.std() + 1e-6)


def paint_wall(rng: np.random.Generator, width: int, height: int, res: float) -> np.ndarray:
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
    wall += 12 * smooth_noise(rng, wall.shape, 6.0) + 6 * smooth_noise(rng, wall.shape, 1.0)
    return wall


def paint_plane(rng: np.random.Generator, shape: tuple[int, int], res: float, tile: float, base: float, spread: float) -> np.ndarray:
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
    plane += 8 * smooth_noise(rng, plane.shape, 4.0) + 5 * smooth_noise(rng, plane.shape, 1.0)
    return plane


def lamp_light(points: np.ndarray, lamps: np.ndarray, height_below_lamp: np.ndarray | float) -> np.ndarray:
    """Illumination gain at points ``height_below_lamp`` under the ceiling, from ceiling lamps
    at ``lamps`` (x, y): ambient plus a smooth inverse-square falloff 1/(1 + d²/2 m²)."""
    below2 = np.asarray(height_below_lamp, np.float32) ** 2
    gain = sum(0.9 / (1.0 + (((points - lamp) ** 2).sum(axis=-1) + below2) / 2.0) for lamp in lamps)
    return np.minimum(0.45 + gain, 1.25).astype(np.float32)
