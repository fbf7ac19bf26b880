"""The experience map (Milford & Wyeth 2008/2010), a pure core: numbers in, numbers out.

Per frame it takes the path integrator's pose in its odometry frame (x, y, heading), the
frame's view template id, and a confirmed loop closure when there is one:

- The robot is always "at" a current experience, at an offset (in that experience's frame)
  given by the odometry travelled since it was last there.
- A new experience is made when that offset exceeds `new_experience_distance` or the view
  template changes; it is linked from the current one by the offset.
- A confirmed loop closure links the current experience to the experience of the matched
  template (the one made at the matched frame, else the latest with that template) by the
  offset, and makes that experience current: the robot is where it was before.
- Relaxation (RatSLAM's graph relaxation): every link pulls both of its ends toward agreement
  with the link's transform by `correction` (0.5, as in RatSLAM) of the disagreement; headings
  are relaxed the same way. All links act at once and a node's pulls are averaged over its
  links, so the result does not depend on link order and the vectorised update is stable.

Everything is deterministic: the same inputs in the same order give the same map, which is
what lets a restarted service rebuild its map by replaying the log of its inputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from services.common.errors import ConfigError


@dataclass(frozen=True)
class MapParams:
    new_experience_distance: float = 1.0   # metres of odometry before a new experience
    correction: float = 0.5                # RatSLAM's correction factor
    relax_passes: int = 10                 # relaxation passes per frame after a loop closure
    relax_every_frame: int = 1             # passes on frames without a loop closure

    def check(self) -> None:
        for name, ok in (("new_experience_distance", self.new_experience_distance > 0),
                         ("correction", 0 < self.correction <= 1), ("relax_passes", self.relax_passes >= 0),
                         ("relax_every_frame", self.relax_every_frame >= 0)):
            if not ok:
                raise ConfigError(f"experience map: invalid {name} = {getattr(self, name)!r}")


def wrap(angle):
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def compose(pose: tuple[float, float, float], offset: tuple[float, float, float]) -> tuple[float, float, float]:
    """pose ∘ offset for planar poses (x, y, heading)."""
    x, y, th = pose
    dx, dy, dth = offset
    c, s = math.cos(th), math.sin(th)
    return x + c * dx - s * dy, y + s * dx + c * dy, float(wrap(th + dth))


def between(a: tuple[float, float, float], b: tuple[float, float, float]) -> tuple[float, float, float]:
    """The offset of b in a's frame: a ∘ between(a, b) = b."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    c, s = math.cos(a[2]), math.sin(a[2])
    return c * dx + s * dy, -s * dx + c * dy, float(wrap(b[2] - a[2]))


@dataclass(frozen=True)
class Link:
    source: int
    target: int
    dx: float
    dy: float
    dheading: float
    frame: int
    loop_closure: bool = False


@dataclass
class FrameResult:
    """What one frame did to the map."""

    frame: int
    experience: int
    pose: tuple[float, float, float]          # the robot's map pose
    new_experiences: list[int] = field(default_factory=list)
    new_links: list[Link] = field(default_factory=list)
    moved: list[int] = field(default_factory=list)   # experiences moved by relaxation beyond 1 mm / 0.1 mrad


class ExperienceMap:
    def __init__(self, params: MapParams = MapParams()):
        params.check()
        self.params = params
        self.poses = np.zeros((0, 3))                   # experience map poses (x, y, heading)
        self.templates: list[int] = []
        self.created: list[int] = []                    # frame of creation
        self.links: list[Link] = []
        self.current: int | None = None
        self.anchor: tuple[float, float, float] | None = None   # odometry pose when last at `current`
        self.frames: list[tuple[int, int, tuple[float, float, float]]] = []   # (frame, experience, offset)
        self.last_frame: int | None = None

    def __len__(self) -> int:
        return len(self.templates)

    def step(self, frame: int, odometry: tuple[float, float, float], template_id: int,
             closure: tuple[int, int] | None = None) -> FrameResult:
        """Apply one frame: odometry pose (x, y, heading), its view template, and an optional
        confirmed closure (matched_template, matched_frame)."""
        if not all(math.isfinite(v) for v in odometry):
            raise ValueError(f"frame {frame}: odometry pose {odometry} is not finite")
        before = self.poses.copy()
        result = FrameResult(frame, -1, (0.0, 0.0, 0.0))
        if self.current is None:
            self._add_experience(odometry, template_id, frame, result)   # the map starts as the odometry frame
            self.current, self.anchor = 0, odometry
        offset = between(self.anchor, odometry)
        passes = self.params.relax_every_frame
        if closure is not None:
            target = self._experience_of(*closure)
            if target is not None and target != self.current:
                self._link(self.current, target, offset, frame, True, result)
                self.current, self.anchor, offset = target, odometry, (0.0, 0.0, 0.0)
                passes = self.params.relax_passes
        if math.hypot(offset[0], offset[1]) > self.params.new_experience_distance or \
                template_id != self.templates[self.current]:
            new = self._add_experience(compose(tuple(self.poses[self.current]), offset), template_id, frame, result)
            self._link(self.current, new, offset, frame, False, result)
            self.current, self.anchor, offset = new, odometry, (0.0, 0.0, 0.0)
        self.relax(passes)
        moved = np.flatnonzero((np.abs(self.poses[:len(before)] - before) > [1e-3, 1e-3, 1e-4]).any(axis=1))
        result.moved = [int(i) for i in moved if i not in result.new_experiences]
        result.experience = self.current
        result.pose = compose(tuple(self.poses[self.current]), offset)
        self.frames.append((frame, self.current, offset))
        self.last_frame = frame
        return result

    def relax(self, passes: int) -> None:
        if not self.links or passes <= 0:
            return
        source = np.array([link.source for link in self.links])
        target = np.array([link.target for link in self.links])
        offset = np.array([(link.dx, link.dy, link.dheading) for link in self.links])
        degree = np.bincount(np.concatenate([source, target]), minlength=len(self.poses)).astype(float)
        degree[degree == 0] = 1
        for _ in range(passes):
            start = self.poses[source]
            c, s = np.cos(start[:, 2]), np.sin(start[:, 2])
            predicted = np.column_stack([start[:, 0] + c * offset[:, 0] - s * offset[:, 1],
                                         start[:, 1] + s * offset[:, 0] + c * offset[:, 1],
                                         start[:, 2] + offset[:, 2]])
            error = predicted - self.poses[target]
            error[:, 2] = wrap(error[:, 2])
            pull = np.zeros_like(self.poses)
            np.add.at(pull, target, error * self.params.correction)
            np.add.at(pull, source, -error * self.params.correction)
            self.poses += pull / degree[:, None]
            self.poses[:, 2] = wrap(self.poses[:, 2])

    def trajectory(self) -> list[tuple[int, float, float, float]]:
        """(frame, x, y, heading) of every frame, placed on the current (relaxed) map."""
        return [(frame, *compose(tuple(self.poses[experience]), offset)) for frame, experience, offset in self.frames]

    def _experience_of(self, matched_template: int, matched_frame: int) -> int | None:
        candidates = [i for i, t in enumerate(self.templates) if t == matched_template]
        at_frame = [i for i in candidates if self.created[i] == matched_frame]
        return (at_frame or candidates or [None])[-1]

    def _add_experience(self, pose, template_id: int, frame: int, result: FrameResult) -> int:
        self.poses = np.vstack([self.poses, pose])
        self.templates.append(template_id)
        self.created.append(frame)
        result.new_experiences.append(len(self.templates) - 1)
        return len(self.templates) - 1

    def _link(self, source: int, target: int, offset, frame: int, loop_closure: bool, result: FrameResult) -> None:
        link = Link(source, target, float(offset[0]), float(offset[1]), float(offset[2]), frame, loop_closure)
        self.links.append(link)
        result.new_links.append(link)
