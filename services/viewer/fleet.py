"""What the viewer shows of a fleet (docs/fleet.md), as plain numbers: the pure core behind the
viewer's `--fleet` (`[viewer] fleet`). Nothing here knows Zenoh, msgpack or HTTP; the adapter
(service.py) calls one `on_*` per message under its lock.

The fleet map publishes every robot's pose in the fleet frame (`fleet/<robot>/pose`, with
`joined`), its changes (`fleet/update`: the robots, experiences made or moved, closures decided)
and answers `fleet/snapshot` (the whole map). Each robot gets:

- a `Track` (state.py's) of its published fleet poses. A robot not joined yet is posed in the
  frame of its own part of the fleet map, not in the fleet frame: its track is kept but marked
  `joined: false` (the page lists it apart and does not draw it in the fleet frame), and when it
  joins, or a join is split, its track starts afresh, since the old points are in another frame;
- its experiences as the fleet map has them (in its part's frame: the fleet frame once joined);
- the inter-robot closures of the fleet map, by fate (accepted, rejected, pending, unmeasured).

A snapshot replaces what is held (the viewer asks for one at start and when the fleet map's
liveliness token comes back: a restarted fleet map); updates then keep it current.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from services.common.settings import setting
from services.viewer.state import Track, _r

FATES = ("accepted", "rejected", "pending", "unmeasured")


@dataclass(frozen=True)
class FleetViewParams:
    """The viewer's fleet setting (declared once: `[viewer] fleet`, `GRIDSLAM_VIEWER_FLEET`, `--fleet`)."""

    LABEL = "[viewer]"

    fleet: bool = setting(False, help="Also show the fleet (docs/fleet.md): every robot's path and pose in the fleet "
                                      "frame, its experiences and the inter-robot closures, from the fleet map "
                                      "(fleet/<robot>/pose, fleet/update, fleet/snapshot).")


@dataclass
class FleetRobotView:
    """One robot of the fleet as the page shows it."""

    name: str
    track: Track
    joined: bool = False
    joined_at: int | None = None
    part: str | None = None            # the robot whose frame its part of the fleet map is in
    experiences: dict[int, tuple[float, float]] = field(default_factory=dict)
    experience_id: int | None = None   # the experience of its last pose


@dataclass
class FleetCursor:
    """What one browser holds of the fleet."""

    tracks: dict[str, tuple[int, int]] = field(default_factory=dict)   # robot → (epoch, points held)
    map_revision: int = -1


class FleetView:
    """The newest state of the fleet map, fed message by message (numbers in)."""

    def __init__(self, max_points: int = 4000):
        if max_points < 2:
            raise ValueError(f"fleet view: max_points {max_points} < 2")
        self.max_points = max_points
        self.robots: dict[str, FleetRobotView] = {}
        self.links: dict[tuple[str, int], tuple[int, str, int, str]] = {}   # (robot, index) → (exp, matched robot, exp, fate)
        self.map_revision = 0
        self.revision = 0
        self.snapshots = 0              # snapshots applied

    def _robot(self, name: str) -> FleetRobotView:
        robot = self.robots.get(name)
        if robot is None:
            robot = self.robots[name] = FleetRobotView(name, Track(self.max_points))
        return robot

    def _set_joined(self, robot: FleetRobotView, joined: bool) -> None:
        """A change of frame: the track's points were in the other one, start afresh."""
        if joined != robot.joined:
            robot.joined = joined
            robot.track.reset()
            self.map_revision += 1

    # ----------------------------------------------------------------- inputs
    def on_pose(self, robot: str, seq: int, x: float, y: float, heading: float, experience_id: int, joined: bool) -> None:
        """`fleet/<robot>/pose`: the robot's pose in the fleet frame (joined) or in its own part's
        frame. A pose of a recent frame already drawn is one sent again (the robot's source re-sent
        its frames in flight, and its map its map/pose): dropped, not a new run's first."""
        view = self._robot(robot)
        if view.track.again(seq):
            return
        self._set_joined(view, joined)
        view.track.add(seq, x, y, heading)
        view.experience_id = experience_id
        self.revision += 1

    def on_robots(self, robots: list[dict]) -> None:
        """The robots of a FleetUpdate or FleetSnapshot: `{name, joined, joined_at, part, experiences}`."""
        for row in robots:
            view = self._robot(row["name"])
            self._set_joined(view, bool(row["joined"]))
            view.joined_at, view.part = row.get("joined_at"), row.get("part")
        self.revision += 1

    def on_update(self, robots: list[dict], experiences: list[tuple[str, int, float, float]],
                  links: list[tuple[str, int, int, str, int, str]]) -> None:
        """`fleet/update`: the robots, experiences made or moved (robot, id, x, y), closures decided
        (robot, index, experience, matched robot, matched experience, fate)."""
        self.on_robots(robots)
        for robot, ident, x, y in experiences:
            self._robot(robot).experiences[ident] = (_r(x), _r(y))
        for robot, index, experience, matched_robot, matched_experience, fate in links:
            self.links[(robot, index)] = (experience, matched_robot, matched_experience, fate)
        if experiences or links:
            self.map_revision += 1

    def on_snapshot(self, robots: list[dict], experiences: list[tuple[str, int, float, float]],
                    links: list[tuple[str, int, int, str, int, str]]) -> None:
        """`fleet/snapshot`: the whole fleet map; replaces the experiences and closures held."""
        for view in self.robots.values():
            view.experiences = {}
        self.links = {}
        self.on_update(robots, experiences, links)
        self.snapshots += 1
        self.map_revision += 1

    # ----------------------------------------------------------------- output
    def closure_counts(self) -> dict[str, int]:
        counts = dict.fromkeys(FATES, 0)
        for _, _, _, fate in self.links.values():
            counts[fate] = counts.get(fate, 0) + 1
        return counts

    def view(self, cursor: FleetCursor | None = None, include_map: bool = True) -> dict:
        """The fleet's JSON: each robot's track tail since what `cursor` holds, whether it is joined,
        and (when changed, `include_map`) every robot's experiences and the closures between the
        robots whose experiences the fleet map holds."""
        cursor = cursor if cursor is not None else FleetCursor()
        robots = {}
        for name, robot in sorted(self.robots.items()):
            track = robot.track
            epoch, sent = cursor.tracks.get(name, (None, 0))
            tail = track.tail(epoch, sent)
            cursor.tracks[name] = (track.epoch, len(track.points))
            robots[name] = {"joined": robot.joined, "joined_at": robot.joined_at, "part": robot.part,
                            "experiences": len(robot.experiences), "experience_id": robot.experience_id,
                            "track": tail}
        state = {"robots": robots, "closures": self.closure_counts(), "snapshots": self.snapshots}
        if include_map and cursor.map_revision != self.map_revision:
            state["map"] = {
                "revision": self.map_revision,
                "experiences": {name: [[i, x, y] for i, (x, y) in sorted(robot.experiences.items())]
                                for name, robot in sorted(self.robots.items())},
                "links": [[robot, experience, matched_robot, matched_experience, fate]
                          for (robot, _), (experience, matched_robot, matched_experience, fate) in sorted(self.links.items())],
            }
            cursor.map_revision = self.map_revision
        return state
