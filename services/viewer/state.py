"""What the live viewer shows, as plain numbers and arrays (the pure core of the viewer).

The adapter decodes messages and calls one `on_*` method per message; HTTP threads call
`view()` for the JSON a browser gets. Nothing here knows Zenoh, msgpack, pydantic or HTTP,
and nothing here is thread-safe: the adapter holds one lock around every call.

Trajectories are kept per stage (`STAGES`): the ego-motion increments dead-reckoned for
display, the grid-cell odometry (`grid/pose`), the experience map (`map/pose`) and the ground
truth carried by camera frames. Each is a `Track`: every sample moves the current pose, and
the drawn path keeps every `stride`-th sample; when the path exceeds `max_points` it is
halved (every other point kept) and its `epoch` changes, so a browser that holds the old
epoch is sent the whole path again, and one that holds the current epoch only the new tail.
A `seq` back by more than a frame sent again can be starts the track afresh (a new run on the
same robot); one back by less is a frame sent again (a stage's kept outputs, answering frames its
source re-sent after a stall), drawn already and dropped (common/recovery.py's rules).

A run has finished when the source's status says so (`finished` among its counters: every
frame sent and acknowledged); a service whose liveliness token is gone after a status saying
`stopping` stopped, rather than died.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from statistics import median

import cv2
import numpy as np

from services.common.geometry import planar_from_camera
from services.common.odometry import DeadReckoning, turn_first
from services.common.recovery import new_run, sent_again

STAGES = ("ground_truth", "egomotion", "grid", "map")
LATENCY_SAMPLES = 20        # latency shown is the median of the last this many frames
ARRIVALS_KEPT = 512         # camera-frame arrival times kept for the latency (by seq)
LOOP_CLOSURES_SHOWN = 5     # most recent loop closures listed on the page
PIPELINE_EXCLUDED = ("viewer",)   # services left out of the pipeline totals (a viewer drops frames by design)


@dataclass(frozen=True)
class ViewerParams:
    """Display settings of the state (the adapter's ViewerConfig fills them)."""

    max_points: int = 4000          # drawn points per trajectory before it is halved
    camera_width: int = 320         # camera frames are downsampled to at most this width, pixels
    rate_window_s: float = 2.0      # frame rate over this many seconds of arrivals
    silent_after_s: float = 3.0     # a service with no status for this long is shown as silent


@dataclass
class Track:
    """One stage's trajectory: the decimated path and the current pose."""

    max_points: int
    points: list[tuple[float, float]] = field(default_factory=list)   # rounded to millimetres
    epoch: int = 0
    stride: int = 1                 # one drawn point per this many samples
    samples: int = 0                # samples since the track (re)started
    last_seq: int | None = None
    pose: tuple[float, float, float] | None = None   # x, y (m), heading (rad)

    def again(self, seq: int) -> bool:
        """Whether `seq` is a frame sent again (drawn already)."""
        return sent_again(self.last_seq, seq)

    def restart_if_older(self, seq: int) -> bool:
        """Start afresh when `seq` is a new run's; True if it did."""
        if not new_run(self.last_seq, seq):
            return False
        self.reset()
        return True

    def reset(self) -> None:
        """Start afresh: a browser holding the old epoch is sent the new path whole."""
        self.points, self.stride, self.samples, self.pose, self.last_seq = [], 1, 0, None, None
        self.epoch += 1

    def add(self, seq: int, x: float, y: float, heading: float) -> bool:
        """Append one sample (the caller drops a frame sent again: `again`); True when it started
        the track afresh."""
        restarted = self.restart_if_older(seq)
        self.last_seq = seq
        self.pose = (_r(x), _r(y), _r(heading, 4))
        if self.samples % self.stride == 0:
            self.points.append(self.pose[:2])   # rounded once here, so views only slice
            if len(self.points) > self.max_points:
                self.points = self.points[::2]
                self.stride *= 2
                self.epoch += 1
        self.samples += 1
        return restarted

    def tail(self, epoch: int | None, sent: int) -> dict:
        """The points a browser holding (`epoch`, `sent` points) lacks, as JSON."""
        start = sent if epoch == self.epoch and sent <= len(self.points) else 0
        return {"epoch": self.epoch, "from": start, "points": self.points[start:], "pose": self.pose, "seq": self.last_seq}


@dataclass
class Cursor:
    """What one browser already holds, so that each update sends only what changed."""

    tracks: dict[str, tuple[int, int]] = field(default_factory=dict)   # stage → (epoch, points held)
    map_revision: int = -1
    camera_revision: int = -1
    lattice_revision: int = -1


@dataclass
class ServiceRow:
    """One service instance seen through its liveliness token and its status messages."""

    service: str
    instance: str
    alive: bool = False
    status: dict | None = None      # the counters of its last ServiceStatus
    status_time: float | None = None


class ViewerState:
    """The newest state of one robot's pipeline, fed message by message (numbers in)."""

    def __init__(self, params: ViewerParams = ViewerParams()):
        if params.max_points < 2 or params.camera_width < 8:
            raise ValueError(f"viewer params out of range: {params}")
        self.params = params
        self.tracks = {stage: Track(params.max_points) for stage in STAGES}
        self._dead_reckoning = DeadReckoning()
        # Experience map: id → (x, y); links (source, target) → loop closure flag.
        self.experiences: dict[int, tuple[float, float]] = {}
        self.links: dict[tuple[int, int], bool] = {}
        self.experience_count = 0
        self.link_count = 0
        self.map_revision = 0
        self.map_seq: int | None = None         # frame of the last map update or snapshot applied
        self.current_experience: int | None = None
        self.loop_closures: deque[dict] = deque(maxlen=LOOP_CLOSURES_SHOWN)
        self.route: list[tuple[float, float]] = []   # the last route asked of the map (map/route)
        self.loop_closure_count = 0
        self.template: dict | None = None
        self.grid: dict | None = None          # lattice readout of the last grid/pose
        self.saturations = 0                    # grid poses flagged saturated since the run started
        self.camera: np.ndarray | None = None   # downsampled uint8 grey or BGR
        self.camera_seq: int | None = None
        self._last_camera_seq: int | None = None
        self.camera_revision = 0
        self.lattice: np.ndarray | None = None  # uint8 activity image
        self.lattice_info: dict | None = None
        self.lattice_revision = 0
        self.services: dict[tuple[str, str], ServiceRow] = {}
        self.frame: int | None = None           # newest frame index seen on any topic
        self._frame_times: deque[tuple[float, int]] = deque()
        self._arrivals: dict[int, float] = {}   # camera frame seq → arrival time (monotonic s)
        self._latency: dict[str, deque[float]] = {"grid": deque(maxlen=LATENCY_SAMPLES), "map": deque(maxlen=LATENCY_SAMPLES)}
        self.finished: dict | None = None       # {"frames": sent} once the source said every frame is done
        self.revision = 0                       # bumped by every change, so idle streams can skip a tick

    # ----------------------------------------------------------------- inputs
    def on_egomotion(self, seq: int, forward: float, left: float, yaw: float, now: float) -> None:
        """An ego-motion increment (body frame, SE(2): the translation before the yaw);
        dead-reckoned the way the gridcells baseline does (turned for its turn-first order)."""
        track = self.tracks["egomotion"]
        if track.again(seq):   # dead-reckoned already
            return
        restarted = track.restart_if_older(seq)
        if restarted:
            self._dead_reckoning = DeadReckoning()
        pose = self._dead_reckoning.step(*turn_first(forward, left, yaw), yaw).pose
        track.add(seq, pose.x, pose.y, pose.heading)
        self._saw_frame(seq, now, restarted)

    def on_grid_pose(self, seq: int, x: float, y: float, heading: float, lattice_shift: tuple[float, float],
                     step_length: float, saturated: bool, integrator: str, now: float) -> None:
        if self.tracks["grid"].again(seq):
            return
        if self.tracks["grid"].add(seq, x, y, heading) or self.grid is None:
            self.saturations = 0
        self.saturations += int(saturated)
        self.grid = {"seq": seq, "shift": [_r(lattice_shift[0]), _r(lattice_shift[1])], "step_length": _r(step_length, 4),
                     "saturated": saturated, "integrator": integrator}
        self._arrived("grid", seq, now)
        self._saw_frame(seq, now)

    def on_map_pose(self, seq: int, x: float, y: float, heading: float, experience_id: int, now: float) -> None:
        if self.tracks["map"].again(seq):
            return
        self.tracks["map"].add(seq, x, y, heading)
        self.current_experience = experience_id
        self._arrived("map", seq, now)
        self._saw_frame(seq, now)

    def on_camera_frame(self, seq: int, image: np.ndarray | None, ground_truth: np.ndarray | None, now: float) -> None:
        """A camera frame: `image` already made displayable (`display_image`), `ground_truth`
        the 4×4 camera pose in the first camera's frame (x right, y down, z forward) or None."""
        if sent_again(self._last_camera_seq, seq):   # re-sent by the source: shown already
            return
        restarted = new_run(self._last_camera_seq, seq)
        self._last_camera_seq = seq
        if image is not None:
            self.camera, self.camera_seq = image, seq
            self.camera_revision += 1
        if ground_truth is not None:
            self.tracks["ground_truth"].add(seq, *planar_from_camera(ground_truth))
        self._arrivals[seq] = now
        while len(self._arrivals) > ARRIVALS_KEPT:   # the oldest arrival first (dicts keep insertion order)
            del self._arrivals[next(iter(self._arrivals))]
        self._saw_frame(seq, now, restarted)

    def on_grid_activity(self, seq: int, image: np.ndarray, lattice_shift: tuple[float, float], neurons: int,
                         max_rate: float) -> None:
        self.lattice = image
        self.lattice_info = {"seq": seq, "shift": [_r(lattice_shift[0]), _r(lattice_shift[1])], "neurons": neurons,
                             "max_rate": _r(max_rate, 4), "size": [int(image.shape[1]), int(image.shape[0])]}
        self.lattice_revision += 1
        self.revision += 1

    def on_view_template(self, seq: int, template_id: int, is_new: bool, distance: float, matched_frame: int,
                         template_count: int) -> None:
        self.template = {"seq": seq, "id": template_id, "new": is_new, "distance": _r(distance, 4),
                         "matched_frame": matched_frame, "count": template_count}
        self.revision += 1

    def on_loop_closure(self, frame: int, matched_frame: int, matched_template: int, votes: int) -> None:
        self.loop_closures.appendleft({"frame": frame, "matched_frame": matched_frame, "template": matched_template,
                                       "votes": votes})
        self.loop_closure_count += 1
        self.revision += 1

    def on_map_update(self, seq: int, experiences: list[tuple[int, float, float]], links: list[tuple[int, int, int]],
                      experience_count: int, link_count: int) -> bool:
        """Experiences created or moved and links created at frame `seq`. Returns True when the
        map held here has fewer experiences or links than the update says the map has (some
        updates were missed: ask for a snapshot)."""
        for experience_id, x, y in experiences:
            self.experiences[experience_id] = (_r(x), _r(y))
        for source, target, kind in links:
            self.links[(source, target)] = kind
        self.experience_count, self.link_count = experience_count, link_count
        self.map_seq = seq
        self._map_changed()
        return len(self.experiences) < experience_count or len(self.links) < link_count

    def on_route(self, points: list[tuple[float, float]]) -> None:
        """The last route planned on the map (its experiences' positions, start to goal)."""
        self.route = list(points)
        self._map_changed()

    def on_map_snapshot(self, seq: int, experiences: list[tuple[int, float, float]],
                        links: list[tuple[int, int, int]]) -> None:
        """The whole map as of frame `seq` (the `map/snapshot` reply). It replaces what is held,
        unless updates newer than it were applied meanwhile: then it only fills in what is missing."""
        if self.map_seq is None or seq >= self.map_seq:
            self.experiences = {experience_id: (_r(x), _r(y)) for experience_id, x, y in experiences}
            self.links = {(source, target): kind for source, target, kind in links}
            self.map_seq = seq
        else:
            for experience_id, x, y in experiences:
                self.experiences.setdefault(experience_id, (_r(x), _r(y)))
            for source, target, kind in links:
                self.links.setdefault((source, target), kind)
        self.experience_count = max(self.experience_count, len(self.experiences))
        self.link_count = max(self.link_count, len(self.links))
        self._map_changed()

    def _map_changed(self) -> None:
        self.map_revision += 1
        self.revision += 1

    def on_liveliness(self, service: str, instance: str, alive: bool) -> None:
        self._service(service, instance).alive = alive
        self.revision += 1

    def on_status(self, service: str, instance: str, counters: dict, now: float) -> None:
        """A ServiceStatus: `counters` has state, received, published, decode_errors, gaps, stale,
        uptime and optionally `extra` (service-specific counters)."""
        row = self._service(service, instance)
        row.status, row.status_time = dict(counters), now
        if service == "source":
            extra = counters.get("extra") or {}
            self.finished = {"frames": int(extra.get("frames_sent", 0))} if extra.get("finished") else None
        self.revision += 1

    # ----------------------------------------------------------------- output
    def view(self, now: float, cursor: Cursor | None = None, *, include_map: bool = True,
             include_images: bool = True) -> dict:
        """The JSON-ready state for one browser. With a `cursor`, trajectories carry only the
        points it lacks and the map only when it changed (and `include_map`); the cursor is
        advanced to what this view holds. Without one, everything."""
        cursor = cursor if cursor is not None else Cursor()
        tracks = {}
        for stage, track in self.tracks.items():
            epoch, sent = cursor.tracks.get(stage, (None, 0))
            tracks[stage] = track.tail(epoch, sent)
            cursor.tracks[stage] = (track.epoch, len(track.points))
        state = {
            "counters": self.counters(now),
            "tracks": tracks,
            "current_experience": self.current_experience,
            "grid": self.grid,
            "template": self.template,
            "loop_closures": list(self.loop_closures),
            "services": self.service_rows(now),
        }
        if include_map and cursor.map_revision != self.map_revision:
            state["map"] = {
                "revision": self.map_revision,
                "experiences": [(i, x, y) for i, (x, y) in sorted(self.experiences.items())],
                "links": [[s, t, int(loop)] for (s, t), loop in self.links.items()],
                "route": [[x, y] for x, y in self.route],
            }
            cursor.map_revision = self.map_revision
        if include_images:
            if self.camera is not None and cursor.camera_revision != self.camera_revision:
                state["camera"] = {"revision": self.camera_revision, "seq": self.camera_seq,
                                   "size": [int(self.camera.shape[1]), int(self.camera.shape[0])]}
                cursor.camera_revision = self.camera_revision
            if self.lattice is not None and cursor.lattice_revision != self.lattice_revision:
                state["lattice"] = {"revision": self.lattice_revision, **self.lattice_info}
                cursor.lattice_revision = self.lattice_revision
        return state

    def counters(self, now: float) -> dict:
        """The numbers at the top of the page."""
        pipeline = [row.status for row in self.services.values()
                    if row.status is not None and row.service not in PIPELINE_EXCLUDED]
        every = [row.status for row in self.services.values() if row.status is not None]
        latency_stage = "map" if self._latency["map"] else "grid"
        samples = self._latency[latency_stage]
        last_time = self._frame_times[-1][0] if self._frame_times else None
        return {
            "frame": self.frame,
            "rate_hz": _r(self.rate(now), 2),
            "since_last_frame_s": None if last_time is None else _r(now - last_time, 2),
            "latency_ms": _r(1000 * median(samples), 1) if samples else None,
            "latency_stage": latency_stage if samples else None,
            "loop_closures": self.loop_closure_count,
            "loop_closure_links": sum(kind == 1 for kind in self.links.values()),
            "experiences": self.experience_count,
            "links": self.link_count,
            "templates": None if self.template is None else self.template["count"],
            "decode_errors": sum(status["decode_errors"] for status in every),
            "gaps": sum(status["gaps"] for status in pipeline),
            "saturations": self.saturations,
            "services_alive": sum(row.alive for row in self.services.values()),
            "finished": self.finished,
        }

    def rate(self, now: float) -> float:
        """Frames per second over the last `rate_window_s` (0 when the pipeline stalls)."""
        first = next((entry for entry in self._frame_times if now - entry[0] <= self.params.rate_window_s), None)
        last = self._frame_times[-1] if self._frame_times else None
        if first is None or last[0] <= first[0]:
            return 0.0
        return (last[1] - first[1]) / (last[0] - first[0])

    def service_rows(self, now: float) -> list[dict]:
        rows = []
        for (service, instance), row in sorted(self.services.items()):
            # A token without status messages (the router) is not silent; one whose status stopped is.
            silent = row.status_time is not None and now - row.status_time > self.params.silent_after_s
            # Gone after saying it was stopping: it stopped (at the end of a run, say), it did not die.
            stopped = not row.alive and row.status is not None and row.status.get("state") == "stopping"
            state = {"state": "stopped"} if stopped else {}
            rows.append({"service": service, "instance": instance, "alive": row.alive, "silent": silent and not stopped,
                         "stopped": stopped, **(row.status or {}), **state})
        return rows

    # ----------------------------------------------------------------- internals
    def _service(self, service: str, instance: str) -> ServiceRow:
        return self.services.setdefault((service, instance), ServiceRow(service, instance))

    def _saw_frame(self, seq: int, now: float, restarted: bool = False) -> None:
        """Advance the frame counter. Later stages lag the first ones by a few frames, so only
        a topic whose own seq went far back (`restarted`) means a new run."""
        self.revision += 1
        if self.frame is not None and seq < self.frame and restarted:
            self._frame_times.clear()   # a new run: count its frames from here
            self.finished = None
            self._arrivals = {s: t for s, t in self._arrivals.items() if s <= seq}
        elif self.frame is not None and seq <= self.frame:
            return
        self.frame = seq
        self._frame_times.append((now, seq))
        while self._frame_times and now - self._frame_times[0][0] > self.params.rate_window_s:
            self._frame_times.popleft()

    def _arrived(self, stage: str, seq: int, now: float) -> None:
        """Latency: from the viewer's receipt of camera frame `seq` to its receipt of `stage`'s pose for it."""
        arrival = self._arrivals.get(seq)
        if arrival is not None and now >= arrival:
            self._latency[stage].append(now - arrival)


def encode_lattice_png(activity: np.ndarray) -> bytes:
    """The activity image in false colour (viridis: dark = silent, yellow = the bumps)."""
    ok, data = cv2.imencode(".png", cv2.applyColorMap(activity, cv2.COLORMAP_VIRIDIS))
    if not ok:
        raise ValueError("PNG encoding failed")
    return data.tobytes()


def _r(value: float, digits: int = 3) -> float:
    """Rounded for JSON (millimetres for positions); keeps the payload compact."""
    return round(float(value), digits)
