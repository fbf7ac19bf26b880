"""The ``campus`` layout of the synthetic world: a network of corridors and a route through it.

Four loops of different shapes share junctions (docs/sources.md has the plot, ``gridslam
world --preset campus --plot FILE`` draws it): a 28 m × 24 m rectangle (A), a 36 m × 24 m
rectangle beside it (B), an L-shaped loop below them (C) and a long thin loop with a curved
end (D, 36 m long, 12 m across, a half circle of 6 m radius), joined at T junctions and one
X crossing. The route is a closed tour of about 2.2 km through it: every loop is driven
several times, in both directions, so most stretches are revisited in the same direction and
many in the opposite one. Two pairs of straight stretches (20 m and 17 m) are look-alikes:
walls, pillars, floor, ceiling and lamps of one are a translated copy of the other's
(``twins``), 69 m and 37 m apart.

The geometry is fixed; the seed draws the textures, the pillars, the lamps' schedules, the
noise and the sway. Everything is in metres, x east, y north; the corridor width is the
world's ``corridor_width``. Walls come from a 2 cm raster of the free space (corridors as
rectangles with square ends at corners and junctions, the curved end as an annulus sector,
pillars cut out), traced by ``cv2.findContours``: straight walls and corners exactly, curved
walls as chords within two pixels. The route turns at every corner with a radius of half the
corridor width, as the corridor world does.

Pure geometry (numpy and OpenCV): ``campus_layout(corridor_width, pillar_spacing, rng)``
returns a ``Layout`` the world renders (services/source/synthetic.py).
"""

from __future__ import annotations

import math
import cv2
import numpy as np

from services.common.geometry import wrap
from services.source.world.layout import LAMP_SPACING, PILLAR_SIZE, RASTER, Layout, Twin, in_region
from services.source.world.route import Route

# Junctions and corners (x, y); the loops: A = a b e d, B = b c r f e, C = a g h i j b,
# D = c p q r (p→q is the curved end).
NODES: dict[str, tuple[float, float]] = {
    "a": (0.0, 0.0), "b": (28.0, 0.0), "c": (64.0, 0.0), "p": (100.0, 0.0),
    "d": (0.0, 24.0), "e": (28.0, 24.0), "f": (64.0, 24.0),
    "r": (64.0, 12.0), "q": (100.0, 12.0),
    "g": (0.0, -24.0), "h": (46.0, -24.0), "i": (46.0, -12.0), "j": (28.0, -12.0),
}
# Curved corridors: (from, to) → (centre, radius), counter-clockwise from `from` to `to`.
ARCS: dict[tuple[str, str], tuple[tuple[float, float], float]] = {("p", "q"): ((100.0, 6.0), 6.0)}
# The route, one pass per string; the tour is closed (the last node joins the first) and
# starts half-way along a→b heading east.
TOUR = (
    "a b e d",                      # A counter-clockwise
    "a b c r f e d",                # around A and B
    "a g h i j b",                  # C counter-clockwise; b→a westward, against the first passes
    "a d e f r q p c b j i h g",    # D and C clockwise: mostly against the earlier passes
    "a b e f r c p q r f e d",      # D counter-clockwise
    "a g h i j b c p q r f e b",    # C and D counter-clockwise again
    "a d e b c r q p c b",          # A clockwise, D clockwise
    "a d e f r c b j i h g",        # B clockwise, C clockwise
    "a b j i h g",                  # C clockwise
    "a d e b j i h g",              # A clockwise half, through the X crossing at b, C clockwise
)
ROUTE_START = 0.5  # fraction of the first edge (a→b) where the route starts


def twins(corridor_width: float) -> tuple[Twin, ...]:
    """The two look-alike pairs: 20 m of the d–e corridor copied onto q–r, 17 m of b–e onto a–g."""
    across = corridor_width / 2 + 0.5  # the walls and the pillars against them
    return (
        Twin((4.0, 24.0, 24.0 - across, 24.0 + across), (68.0, -12.0)),
        Twin((28.0 - across, 28.0 + across, 3.5, 20.5), (-28.0, -24.0)),
    )


CURVE_TOLERANCE = 2.0  # pixels: a curved wall's segments stay this close to its traced (4-connected) stairs


def tour_nodes() -> list[str]:
    return " ".join(TOUR).split()


def edges() -> list[tuple[str, str]]:
    """Every corridor once, in the order the tour first drives it."""
    nodes = tour_nodes()
    seen: dict[frozenset, tuple[str, str]] = {}
    for a, b in zip(nodes, nodes[1:] + nodes[:1]):
        seen.setdefault(frozenset((a, b)), (a, b))
    return list(seen.values())


def _arc(a: str, b: str) -> tuple[tuple[float, float], float, int] | None:
    """(centre, radius, +1 counter-clockwise / −1 clockwise) when a→b is a curved corridor."""
    if (a, b) in ARCS:
        return (*ARCS[(a, b)], 1)
    if (b, a) in ARCS:
        return (*ARCS[(b, a)], -1)
    return None


def _headings(a: str, b: str) -> tuple[float, float, float]:
    """Heading leaving a, heading arriving at b, and the length of the corridor a→b."""
    (xa, ya), (xb, yb) = NODES[a], NODES[b]
    arc = _arc(a, b)
    if arc is None:
        heading = math.atan2(yb - ya, xb - xa)
        return heading, heading, math.hypot(xb - xa, yb - ya)
    (cx, cy), radius, sense = arc
    start, end = math.atan2(ya - cy, xa - cx), math.atan2(yb - cy, xb - cx)
    sweep = (end - start) % (2 * math.pi) if sense > 0 else (start - end) % (2 * math.pi)
    return start + sense * math.pi / 2, end + sense * math.pi / 2, radius * sweep


def build_route(corridor_width: float) -> Route:
    """The tour as (length, curvature) pieces: straight corridors, the curved end, and a
    turn of radius corridor_width / 2 at every corner."""
    nodes = tour_nodes()
    legs = list(zip(nodes, nodes[1:] + nodes[:1]))
    radius = corridor_width / 2
    turns, trims = [], []
    for k, (a, b) in enumerate(legs):
        arriving = _headings(*legs[k - 1])[1]
        turn = wrap(_headings(a, b)[0] - arriving)
        if abs(turn) > math.radians(100):
            raise AssertionError(f"campus tour: turn of {math.degrees(turn):.0f}° at {a}")
        if turn and (_arc(a, b) or _arc(*legs[k - 1])):
            raise AssertionError(f"campus tour: a turn at {a}, where a curved corridor ends")
        turns.append(turn)
        trims.append(radius * math.tan(abs(turn) / 2))
    pieces: list[tuple[float, float]] = []
    for k, (a, b) in enumerate(legs):
        if turns[k]:
            pieces.append((radius * abs(turns[k]), math.copysign(1 / radius, turns[k])))
        arc = _arc(a, b)
        length = _headings(a, b)[2]
        if arc:
            pieces.append((length, arc[2] / arc[1]))
        else:
            straight = length - trims[k] - trims[(k + 1) % len(legs)]
            if straight < 0:
                raise AssertionError(f"campus tour: {a}→{b} is too short for its turns")
            pieces.append((straight, 0.0))
    # Start part-way along the first corridor (after its turn): split that piece in two.
    first = 1 if turns[0] else 0
    length = pieces[first][0]
    head, tail = ROUTE_START * length, (1 - ROUTE_START) * length
    heading = _headings(*legs[0])[0]
    xa, ya = NODES[legs[0][0]]
    offset = trims[0] + head
    start = (xa + offset * math.cos(heading), ya + offset * math.sin(heading), heading)
    ordered = [(tail, 0.0)] + pieces[first + 1:] + pieces[:first] + [(head, 0.0)]
    return Route.from_pieces(ordered, start)


def _free_space(corridor_width: float, pillars: list[tuple[float, float, float, float]]) -> tuple[np.ndarray, tuple[float, float]]:
    """Raster of the corridors (1 free, 0 wall) and the world position of pixel (0, 0)."""
    half = corridor_width / 2
    xs, ys = zip(*NODES.values())
    reach = max(radius for _, radius in ARCS.values()) + half + 1.0
    x0 = RASTER * math.floor((min(xs) - half - 1.0) / RASTER)
    y0 = RASTER * math.floor((min(ys) - half - 1.0) / RASTER)
    x1, y1 = max(xs) + reach, max(ys) + half + 1.0
    free = np.zeros((int((y1 - y0) / RASTER) + 1, int((x1 - x0) / RASTER) + 1), np.uint8)

    def px(x: float, y: float) -> tuple[int, int]:
        return int(round((x - x0) / RASTER)), int(round((y - y0) / RASTER))

    smooth = {node for pair in ARCS for node in pair}  # a curved corridor continues there: no square end
    for a, b in edges():
        arc = _arc(a, b)
        if arc is None:
            (xa, ya), (xb, yb) = NODES[a], NODES[b]
            ux, uy = (xb - xa) / math.hypot(xb - xa, yb - ya), (yb - ya) / math.hypot(xb - xa, yb - ya)
            ea, eb = (0.0 if a in smooth else half), (0.0 if b in smooth else half)
            corners = [(xa - ea * ux - half * uy, ya - ea * uy + half * ux), (xb + eb * ux - half * uy, yb + eb * uy + half * ux),
                       (xb + eb * ux + half * uy, yb + eb * uy - half * ux), (xa - ea * ux + half * uy, ya - ea * uy - half * ux)]
            cv2.fillPoly(free, [np.array([px(*p) for p in corners], np.int32)], 1)
        else:
            (cx, cy), radius, _ = arc
            start = math.atan2(NODES[a][1] - cy, NODES[a][0] - cx)
            _, _, length = _headings(a, b)
            sweep = length / radius * arc[2]
            angles = start + np.linspace(0.0, sweep, 181)
            outer = [(cx + (radius + half) * math.cos(t), cy + (radius + half) * math.sin(t)) for t in angles]
            inner = [(cx + (radius - half) * math.cos(t), cy + (radius - half) * math.sin(t)) for t in angles[::-1]]
            scale = 16  # fixed point with 4 fractional bits: a smooth curve
            polygon = np.array([[round((x - x0) / RASTER * scale), round((y - y0) / RASTER * scale)] for x, y in outer + inner], np.int32)
            cv2.fillPoly(free, [polygon], 1, lineType=cv2.LINE_8, shift=4)
    for left, right, bottom, top in pillars:
        (c0, r0), (c1, r1) = px(left, bottom), px(right, top)
        free[r0:r1 + 1, c0:c1 + 1] = 0
    return free, (x0, y0)


def _pillars(rng: np.random.Generator, corridor_width: float, spacing: float, pairs: tuple[Twin, ...]) -> list[tuple[float, float, float, float]]:
    """Square pillars (x0, x1, y0, y1) against both walls of the straight corridors, away from
    junctions and corners, on the raster grid; inside a twin's copy, the original's copies."""
    if spacing <= 0:
        return []
    half, size = corridor_width / 2, PILLAR_SIZE
    clear = half + 0.6  # keep the junctions and corners free
    pillars = []
    for a, b in edges():
        if _arc(a, b):
            continue
        (xa, ya), (xb, yb) = NODES[a], NODES[b]
        length = math.hypot(xb - xa, yb - ya)
        ux, uy = (xb - xa) / length, (yb - ya) / length
        for side in (-1, 1):
            across = side * (half - size / 2)
            position = clear + rng.uniform(0, spacing)
            while position < length - clear:
                cx, cy = xa + position * ux - across * uy, ya + position * uy + across * ux
                pillars.append(tuple(RASTER * round(v / RASTER) for v in (cx - size / 2, cx + size / 2, cy - size / 2, cy + size / 2)))
                position += rng.uniform(0.6, 1.4) * spacing

    def overlaps(pillar, region, margin=0.1) -> bool:  # or comes within `margin` of it
        return (pillar[0] < region[1] + margin and pillar[1] > region[0] - margin
                and pillar[2] < region[3] + margin and pillar[3] > region[2] - margin)

    def inside(pillar, region, margin=0.1) -> bool:  # and `margin` away from its sides
        return (pillar[0] >= region[0] + margin and pillar[1] <= region[1] - margin
                and pillar[2] >= region[2] + margin and pillar[3] <= region[3] - margin)

    # A copy's own pillars go; so does any pillar on or near the side of a twin's region.
    kept = [p for p in pillars if not any(overlaps(p, t.moved()) or (overlaps(p, t.region) and not inside(p, t.region)) for t in pairs)]
    for twin in pairs:
        dx, dy = twin.offset
        kept += [(p[0] + dx, p[1] + dx, p[2] + dy, p[3] + dy) for p in kept if inside(p, twin.region)]
    return kept


def _outline(contour: np.ndarray, free: np.ndarray) -> np.ndarray:
    """Vertices (pixels) of one traced boundary: the 8-connected trace made 4-connected (a
    diagonal step goes through the free one of its two corner pixels, so a corner is a corner
    whichever way the tracer cut it) and straight runs merged. Corners between two edges of 4
    pixels or more (walls, pillars, junctions) are kept exactly; the stairs of a curved wall
    between such corners are simplified to within CURVE_TOLERANCE pixels."""
    points = contour[:, 0]
    following = np.roll(points, -1, axis=0)
    diagonal = np.all(np.abs(following - points) == 1, axis=1)
    first_corner = np.c_[points[:, 0], following[:, 1]]
    corner = np.where((free[first_corner[:, 1], first_corner[:, 0]] > 0)[:, None], first_corner, np.c_[following[:, 0], points[:, 1]])
    path = np.empty((len(points) + int(diagonal.sum()), 2), int)
    index = np.arange(len(points)) + np.concatenate([[0], np.cumsum(diagonal)[:-1]])
    path[index] = points
    path[index[diagonal] + 1] = corner[diagonal]
    step = np.roll(path, -1, axis=0) - path
    vertices = path[np.any(step != np.roll(step, 1, axis=0), axis=1)]
    edges = np.hypot(*(np.roll(vertices, -1, axis=0) - vertices).T)
    anchors = np.flatnonzero((edges >= 4) & (np.roll(edges, 1) >= 4))  # vertex k: edges k - 1 and k are long
    if len(anchors) == len(vertices):
        return vertices
    if not len(anchors):
        return cv2.approxPolyDP(vertices.reshape(-1, 1, 2).astype(np.int32), CURVE_TOLERANCE, True)[:, 0]
    kept = []
    for a, b in zip(anchors, np.r_[anchors[1:], anchors[0] + len(vertices)]):
        chain = vertices[np.arange(a, b + 1) % len(vertices)]
        if b - a > 1 and edges[np.arange(a, b) % len(vertices)].min() < 4:
            chain = cv2.approxPolyDP(chain.reshape(-1, 1, 2).astype(np.int32), CURVE_TOLERANCE, False)[:, 0]
        kept += list(chain[:-1])
    return np.array(kept)


def _trace_walls(free: np.ndarray, origin: tuple[float, float]) -> np.ndarray:
    """Wall segments (x0, y0, dx, dy) along the boundary of the free space, each directed
    with the free space on its left (so a wall's texture reads the same way wherever it is)."""
    contours, _ = cv2.findContours(free, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    segments = []
    for contour in contours:
        points = np.asarray(origin) + _outline(contour, free).astype(np.float64) * RASTER
        for p, q in zip(points, np.roll(points, -1, axis=0)):
            segments.append((p[0], p[1], q[0] - p[0], q[1] - p[1]))
    segments = np.array(segments)
    middles = segments[:, :2] + segments[:, 2:] / 2
    left = np.c_[-segments[:, 3], segments[:, 2]] / np.hypot(segments[:, 2], segments[:, 3])[:, None]
    probe = middles + 3 * RASTER * left
    col = np.rint((probe[:, 0] - origin[0]) / RASTER).astype(int)
    row = np.rint((probe[:, 1] - origin[1]) / RASTER).astype(int)
    flip = free[np.clip(row, 0, free.shape[0] - 1), np.clip(col, 0, free.shape[1] - 1)] == 0
    segments[flip] = np.c_[segments[flip, :2] + segments[flip, 2:], -segments[flip, 2:]]
    return segments


def _split_at(segments: np.ndarray, regions: list[tuple[float, float, float, float]]) -> np.ndarray:
    """Segments cut where they cross the sides of the regions (x0, x1, y0, y1)."""
    for x0, x1, y0, y1 in regions:
        for axis, value, low, high in ((0, x0, y0, y1), (0, x1, y0, y1), (1, y0, x0, x1), (1, y1, x0, x1)):
            out = []
            for x, y, dx, dy in segments:
                start, delta = (x, y)[axis], (dx, dy)[axis]
                t = (value - start) / delta if delta else -1.0
                across = (y + t * dy, x + t * dx)[axis]
                if 1e-9 < t < 1 - 1e-9 and low <= across <= high:
                    out += [(x, y, t * dx, t * dy), (x + t * dx, y + t * dy, (1 - t) * dx, (1 - t) * dy)]
                else:
                    out.append((x, y, dx, dy))
            segments = np.array(out)
    return segments


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z of the cross product of 2-D vectors (rows)."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _twin_textures(segments: np.ndarray, pairs: tuple[Twin, ...]) -> tuple[np.ndarray, np.ndarray]:
    """For every segment, the segment whose texture it shows and where along that one (metres)
    it starts: inside a twin's copy, the original's wall at the same relative place. (Where a
    wall falls half-way between raster pixels, a copy's wall can lie a pixel off its
    original's and be cut differently: a piece then shows the original's texture from where it
    starts along it; a piece without a counterpart keeps its own texture.)"""
    texture_of, shift = np.arange(len(segments)), np.zeros(len(segments))
    middles = segments[:, :2] + segments[:, 2:] / 2
    tolerance = 2.5 * RASTER
    for twin in pairs:
        originals = np.flatnonzero(in_region(middles, twin.region))
        starts, directions = segments[originals, :2], segments[originals, 2:]
        lengths2 = (directions**2).sum(axis=1)
        for k in np.flatnonzero(in_region(middles, twin.moved())):
            start, direction = segments[k, :2] - np.asarray(twin.offset), segments[k, 2:]
            end = start + direction
            t0 = ((start - starts) * directions).sum(axis=1) / lengths2
            t1 = ((end - starts) * directions).sum(axis=1) / lengths2
            off_line = np.abs(_cross(directions, start - starts)) / np.sqrt(lengths2)
            parallel = np.abs(_cross(directions, direction)) < 1e-9 * np.sqrt(lengths2) * np.hypot(*direction) + 1e-12
            slack = tolerance / np.sqrt(lengths2)
            inside = parallel & (off_line < tolerance) & (t0 >= -slack) & (t1 <= 1 + slack) & (t1 > t0)
            if inside.any():
                j = int(np.flatnonzero(inside)[0])
                texture_of[k] = originals[j]
                shift[k] = t0[j] * math.sqrt(lengths2[j])
    return texture_of, shift


def _lamps(pairs: tuple[Twin, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ceiling lamps every LAMP_SPACING metres along every corridor's centre line: positions,
    headings (of the corridor) and the lamp whose schedule each follows (twins share it)."""
    lamps = []
    for a, b in edges():
        arc = _arc(a, b)
        heading, _, length = _headings(a, b)
        for s in np.arange(LAMP_SPACING / 2, length, LAMP_SPACING):
            if arc is None:
                xa, ya = NODES[a]
                lamps.append((xa + s * math.cos(heading), ya + s * math.sin(heading), heading))
            else:
                (cx, cy), radius, sense = arc
                angle = math.atan2(NODES[a][1] - cy, NODES[a][0] - cx) + sense * s / radius
                lamps.append((cx + radius * math.cos(angle), cy + radius * math.sin(angle), angle + sense * math.pi / 2))
    lamps = np.array(lamps)
    keep = ~np.any([in_region(lamps, t.moved()) for t in pairs], axis=0)
    kept_index = np.cumsum(keep) - 1
    parts, schedule_of = [lamps[keep]], [np.arange(int(keep.sum()))]
    for twin in pairs:
        originals = np.flatnonzero(in_region(lamps, twin.region) & keep)
        parts.append(lamps[originals] + np.array([*twin.offset, 0.0]))
        schedule_of.append(kept_index[originals])
    lamps = np.concatenate(parts)
    schedule_of = np.concatenate(schedule_of)
    return lamps[:, :2], lamps[:, 2], schedule_of


def campus_layout(corridor_width: float, pillar_spacing: float, rng: np.random.Generator) -> Layout:
    """The campus network for a corridor width, its pillars drawn from ``rng``."""
    pairs = twins(corridor_width)
    pillars = _pillars(rng, corridor_width, pillar_spacing, pairs)
    free, origin = _free_space(corridor_width, pillars)
    segments = _trace_walls(free, origin)
    segments = _split_at(segments, [region for twin in pairs for region in (twin.region, twin.moved())])
    lamps, headings, schedule_of = _lamps(pairs)
    texture_of, texture_shift = _twin_textures(segments, pairs)
    return Layout(
        route=build_route(corridor_width), segments=segments, texture_of=texture_of, texture_shift=texture_shift,
        lamps=lamps, lamp_headings=headings, lamp_schedule_of=schedule_of, twins=pairs, free=free, origin=origin,
    )
