"""viewer: watch a run live in a browser (trajectories, experience map, grid-cell lattice, camera).

The viewer is an ordinary external client of the pipeline: it subscribes to the pose topics of
every stage, the map, the loop closures, the lattice and the camera (newest only), the status
topics and the health tokens, and keeps only the newest state (services/viewer/state.py).
An HTTP server in its own threads serves one static page; each browser gets a server-sent
event stream of compact JSON at a bounded rate (trajectories as tails since what it holds,
the map when it changed) and fetches the camera and lattice images from their endpoints. The
pipeline never waits for a browser: a stream that cannot keep up or disconnects only loses
its own updates.
"""

from __future__ import annotations

import argparse
import json
import logging
import socket
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import urlsplit

import zenoh

from schemas import (
    CameraFrame, EgoMotion, FleetPose, FleetSnapshot, FleetUpdate, GridActivity, GridPose, LoopClosure, MapPose, MapRoute,
    MapSnapshot, MapUpdate, ServiceStatus, ViewTemplate,
)
from services.common import codec, topics
from services.common.config import load_config
from services.common.convert import image_from_msg, pose_to_matrix
from services.common.errors import ConfigError
from services.common.observe import map_items, observe
from services.common.runtime import RuntimeConfig, is_loopback
from services.common.service import Service
from services.common.settings import add_field_flag, add_flag
from services.viewer.config import ViewerConfig
from services.viewer.fleet import FleetCursor, FleetView, FleetViewParams
from services.common.images import display_image, encode_camera_jpeg
from services.viewer.state import Cursor, ViewerState, encode_lattice_png

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).resolve().parent / "static"
STATIC_FILES = {   # URL path → (file in static/, content type)
    "/": ("index.html", "text/html; charset=utf-8"),
    "/viewer.js": ("viewer.js", "text/javascript; charset=utf-8"),
    "/viewer.css": ("viewer.css", "text/css; charset=utf-8"),
}
KEEPALIVE_S = 1.0          # an idle stream still gets a state (ages and rates move) this often
SOCKET_TIMEOUT_S = 10.0    # a browser that stops reading for this long loses its stream
SNAPSHOT_RETRY_S = 2.0     # at most one map/snapshot query per this many seconds
SNAPSHOT_TIMEOUT_S = 5.0
# Samples waiting for the main thread. Pose messages are small and newest-only topics queue
# only a marker, so a deep inbox is cheap; it absorbs a pause of the main thread (the GIL held
# while a connecting browser's JSON is encoded) even at thousands of frames per second.
INBOX_SIZE = 4096


class ViewerService(Service):
    name = "viewer"
    observer = True            # never pushes back on the pipeline (issue 8): a full inbox drops
    inbox_size = INBOX_SIZE

    def __init__(self, runtime: RuntimeConfig, config: ViewerConfig, instance: str | None = None):
        super().__init__(runtime, instance)
        self.config = config
        self.viewer_state = ViewerState(config.params())
        self.lock = threading.Lock()            # guards self.viewer_state (main thread, Zenoh and HTTP threads)
        self.http_stop = threading.Event()
        self.stream_slots = threading.BoundedSemaphore(config.max_clients)
        self.static = _read_static()
        self.http = _bind(config, self)         # bind now: a busy port is an error before anything starts
        self._http_thread: threading.Thread | None = None
        self._image_cache: dict[str, tuple[int, bytes]] = {}
        self._map_json: tuple[int, bytes] | None = None   # (map revision, its JSON), shared by all browsers
        self._own_entities: list = []            # status and liveliness subscribers (outside the base's seq checks)
        self._snapshot_wanted = True
        self._snapshot_sent = -SNAPSHOT_RETRY_S
        # --fleet: the fleet map's poses, updates and snapshot (fleet.py), in its key space `fleet`.
        self.fleet = FleetView(config.max_points) if config.fleet else None
        self._fleet_snapshot_wanted = self.fleet is not None
        self._fleet_snapshot_sent = -SNAPSHOT_RETRY_S

    @property
    def url(self) -> str:
        host, port = self.http.server_address[:2]
        return f"http://{f'[{host}]' if ':' in host else host}:{port}/"

    # ----------------------------------------------------------------- life cycle
    def run(self) -> int:
        # The page is up before the session: it shows "waiting" while a router is awaited.
        self.start_http()
        try:
            return super().run()
        finally:
            self.close_http()

    def start_http(self) -> None:
        self._http_thread = threading.Thread(target=self.http.serve_forever, kwargs={"poll_interval": 0.1},
                                             name="viewer-http", daemon=True)
        self._http_thread.start()
        log.info("viewer serving %s", self.url)

    def close_http(self) -> None:
        self.http_stop.set()
        if self._http_thread is not None and self._http_thread.is_alive():
            self.http.shutdown()
        self.http.server_close()

    def setup(self) -> None:
        # A seq far back is a new run, shown afresh; one back by less, a frame sent again (common/recovery.py).
        observe(self, {"egomotion": self.on_egomotion, "grid/pose": self.on_grid_pose, "map/pose": self.on_map_pose,
                       "map/update": self.on_map_update, "loop/closure": self.on_loop_closure,
                       "map/route": self.on_map_route, "camera/frame": self.on_camera_frame,
                       "grid/activity": self.on_grid_activity, "view/template": self.on_view_template})
        # Status messages of many services share one wildcard and carry no frame sequence of their
        # own, so they bypass the base's per-topic seq check; they are small and once a second.
        self._own_entities += [
            self.session.declare_subscriber(topics.key(self.robot, "status/**"), self._on_status_sample),
            self.session.liveliness().declare_subscriber(topics.key(self.robot, "health/**"), self._on_token,
                                                         history=True),
        ]
        if self.fleet is not None:
            self.subscribe(topics.fleet_pose_topic("*"), self.on_fleet_pose, robot=topics.FLEET, drop_stale=False,
                           sparse=True)
            self.subscribe("update", self.on_fleet_update, robot=topics.FLEET, drop_stale=False, sparse=True)
            self._own_entities += [   # the fleet map in the table of services, and its restarts
                self.session.declare_subscriber(topics.key(topics.FLEET, "status/**"), self._on_status_sample),
                self.session.liveliness().declare_subscriber(topics.key(topics.FLEET, "health/**"), self._on_token,
                                                             history=True),
            ]
        self._query_snapshot_if_due()

    def teardown(self) -> None:
        for entity in self._own_entities:
            entity.undeclare()
        self._own_entities = []

    def on_idle(self) -> None:
        self._query_snapshot_if_due()

    # ----------------------------------------------------------------- pipeline topics (main thread)
    def on_egomotion(self, message: EgoMotion) -> None:
        increment = message.increment
        with self.lock:
            self.viewer_state.on_egomotion(message.header.seq, increment.forward, increment.left, increment.yaw,
                                           time.monotonic())

    def on_grid_pose(self, message: GridPose) -> None:
        position = message.pose.position
        with self.lock:
            self.viewer_state.on_grid_pose(message.header.seq, position.x, position.y, message.heading,
                                           message.lattice_shift, message.step_length, message.saturated,
                                           message.integrator, time.monotonic())

    def on_map_pose(self, message: MapPose) -> None:
        position = message.pose.position
        with self.lock:
            self.viewer_state.on_map_pose(message.header.seq, position.x, position.y, message.heading,
                                          message.experience_id, time.monotonic())

    def on_map_update(self, message: MapUpdate) -> None:
        experiences, links = map_items(message)
        with self.lock:
            missing = self.viewer_state.on_map_update(message.header.seq, experiences, links,
                                                      message.experience_count, message.link_count)
        if missing:
            self._snapshot_wanted = True
        self._query_snapshot_if_due()

    def on_loop_closure(self, message: LoopClosure) -> None:
        with self.lock:
            self.viewer_state.on_loop_closure(message.frame, message.matched_frame, message.matched_template,
                                              message.votes)

    def on_map_route(self, message: MapRoute) -> None:
        with self.lock:
            self.viewer_state.on_route([(pose.position.x, pose.position.y) for pose in message.poses])

    def on_camera_frame(self, message: CameraFrame) -> None:
        image = display_image(image_from_msg(message.left), message.left.encoding, self.config.camera_width)
        ground_truth = None if message.ground_truth is None else pose_to_matrix(message.ground_truth)
        with self.lock:
            self.viewer_state.on_camera_frame(message.header.seq, image, ground_truth, time.monotonic())

    def on_grid_activity(self, message: GridActivity) -> None:
        image = display_image(image_from_msg(message.image), message.image.encoding, 512)
        if image.ndim == 3:
            image = image.mean(axis=2).astype(image.dtype)
        with self.lock:
            self.viewer_state.on_grid_activity(message.header.seq, image, message.lattice_shift, message.neurons,
                                               message.max_rate)

    def on_view_template(self, message: ViewTemplate) -> None:
        with self.lock:
            self.viewer_state.on_view_template(message.header.seq, message.template_id, message.is_new,
                                               message.distance, message.matched_frame, message.template_count)

    # ----------------------------------------------------------------- the fleet (main thread)
    def on_fleet_pose(self, message: FleetPose) -> None:
        position = message.pose.position
        with self.lock:
            self.fleet.on_pose(message.header.robot, message.header.seq, position.x, position.y, message.heading,
                               message.experience_id, message.joined)

    def on_fleet_update(self, message: FleetUpdate) -> None:
        robots, experiences, links = fleet_items(message)
        with self.lock:
            self.fleet.on_update(robots, experiences, links)

    # ----------------------------------------------------------------- Zenoh threads
    def _on_status_sample(self, sample: zenoh.Sample) -> None:
        try:
            status = codec.decode(sample.payload.to_bytes(), ServiceStatus, str(sample.encoding))
        except codec.CodecError as error:
            self.counters.decode_errors += 1
            log.warning("viewer: dropped status on %s: %s", sample.key_expr, error)
            return
        counters = status.model_dump(include={"state", "received", "published", "decode_errors", "gaps", "stale", "uptime"})
        counters["uptime"] = round(counters["uptime"], 1)
        counters["extra"] = {name: round(value, 3) for name, value in status.extra.items()}
        with self.lock:
            self.viewer_state.on_status(status.service, status.instance, counters, time.monotonic())

    def _on_token(self, sample: zenoh.Sample) -> None:
        try:
            _, service, instance = topics.parse_health_key(str(sample.key_expr))
        except ValueError:
            return
        alive = sample.kind == zenoh.SampleKind.PUT
        with self.lock:
            self.viewer_state.on_liveliness(service, instance, alive)
        if alive and service == "expmap":   # a (re)started map: fetch what it holds
            self._snapshot_wanted = True
        if alive and service == "fleetmap" and self.fleet is not None:
            self._fleet_snapshot_wanted = True

    def _query_snapshot_if_due(self) -> None:
        now = time.monotonic()
        if self._fleet_snapshot_wanted and now - self._fleet_snapshot_sent >= SNAPSHOT_RETRY_S and self.session is not None:
            self._fleet_snapshot_wanted, self._fleet_snapshot_sent = False, now
            self.session.get(topics.key(topics.FLEET, "snapshot"), self._on_fleet_snapshot_reply,
                             timeout=SNAPSHOT_TIMEOUT_S)
        if not self._snapshot_wanted or now - self._snapshot_sent < SNAPSHOT_RETRY_S or self.session is None:
            return
        self._snapshot_wanted, self._snapshot_sent = False, now
        self.session.get(topics.key(self.robot, "map/snapshot"), self._on_snapshot_reply, timeout=SNAPSHOT_TIMEOUT_S)

    def _on_snapshot_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is None:
            return
        try:
            snapshot = codec.decode(reply.ok.payload.to_bytes(), MapSnapshot, str(reply.ok.encoding))
        except codec.CodecError as error:
            self.counters.decode_errors += 1
            log.warning("viewer: dropped map snapshot: %s", error)
            return
        experiences, links = map_items(snapshot)
        with self.lock:
            self.viewer_state.on_map_snapshot(snapshot.header.seq, experiences, links)

    def _on_fleet_snapshot_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is None:
            return
        try:
            snapshot = codec.decode(reply.ok.payload.to_bytes(), FleetSnapshot, str(reply.ok.encoding))
        except codec.CodecError as error:
            self.counters.decode_errors += 1
            log.warning("viewer: dropped fleet snapshot: %s", error)
            return
        robots, experiences, links = fleet_items(snapshot)
        with self.lock:
            self.fleet.on_snapshot(robots, experiences, links)

    # ----------------------------------------------------------------- HTTP threads
    def view(self, cursor: Cursor | None = None, include_map: bool = True, include_images: bool = True,
             fleet_cursor: FleetCursor | None = None) -> dict:
        with self.lock:
            state = self.viewer_state.view(time.monotonic(), cursor, include_map=include_map,
                                           include_images=include_images)
            if self.fleet is not None:
                state["fleet"] = self.fleet.view(fleet_cursor, include_map=include_map)
        state["robot"] = self.robot
        state["connected"] = self.session is not None
        return state

    def encode(self, state: dict) -> bytes:
        """JSON of a view. The map, the largest part, is encoded once per revision for all browsers."""
        experience_map = state.pop("map", None)
        body = json.dumps(state, separators=(",", ":")).encode()
        if experience_map is None:
            return body
        cached = self._map_json
        if cached is None or cached[0] != experience_map["revision"]:
            cached = self._map_json = (experience_map["revision"], json.dumps(experience_map, separators=(",", ":")).encode())
        return body[:-1] + b',"map":' + cached[1] + b"}"

    def revision(self) -> int:   # int reads: no lock needed
        return self.viewer_state.revision + (0 if self.fleet is None else self.fleet.revision + self.fleet.map_revision)

    def image(self, which: str) -> bytes | None:
        """The newest camera (JPEG) or lattice (PNG) image, encoded once per revision."""
        with self.lock:
            pixels, revision = ((self.viewer_state.camera, self.viewer_state.camera_revision) if which == "camera"
                                else (self.viewer_state.lattice, self.viewer_state.lattice_revision))
        if pixels is None:
            return None
        cached = self._image_cache.get(which)
        if cached is not None and cached[0] == revision:
            return cached[1]
        # The state replaces its arrays and never writes into them, so encoding outside the lock is safe.
        data = encode_camera_jpeg(pixels) if which == "camera" else encode_lattice_png(pixels)
        self._image_cache[which] = (revision, data)
        return data


def _read_static() -> dict[str, tuple[bytes, str]]:
    files = {}
    for url_path, (name, content_type) in STATIC_FILES.items():
        path = STATIC_DIR / name
        if not path.is_file():
            raise ConfigError(f"{path}: the viewer's page is missing from the installation")
        files[url_path] = (path.read_bytes(), content_type)
    return files


class _Server(ThreadingHTTPServer):
    daemon_threads = True       # a stream never holds up the process's exit
    allow_reuse_address = True

    def __init__(self, address: tuple[str, int], viewer: ViewerService):
        self.viewer = viewer
        self.address_family = socket.AF_INET6 if ":" in address[0] else socket.AF_INET
        super().__init__(address, _Handler)


def _bind(config: ViewerConfig, viewer: ViewerService) -> _Server:
    try:
        return _Server(config.address, viewer)
    except OSError as error:
        raise ConfigError(f"viewer: cannot serve on {config.http}: {error.strerror or error}") from None


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    timeout = SOCKET_TIMEOUT_S
    server_version = "gridslam-viewer"

    def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
        viewer = self.server.viewer
        if not self._host_allowed(viewer.config):
            self.send_error(HTTPStatus.FORBIDDEN, "Host not allowed (the viewer serves loopback names only)")
            return
        path = urlsplit(self.path).path
        try:
            if path in viewer.static:
                self._send(*viewer.static[path])
            elif path == "/state.json":
                self._send(viewer.encode(viewer.view()), "application/json")
            elif path == "/events":
                self._stream(viewer)
            elif path in ("/camera.jpg", "/lattice.png"):
                data = viewer.image("camera" if path == "/camera.jpg" else "lattice")
                if data is None:
                    self.send_response(HTTPStatus.NO_CONTENT)
                    self.end_headers()
                else:
                    self._send(data, "image/jpeg" if path.endswith(".jpg") else "image/png")
            else:
                self.send_error(HTTPStatus.NOT_FOUND)
        except (BrokenPipeError, ConnectionResetError, TimeoutError):
            pass   # the browser went away: nothing to clean up

    def _host_allowed(self, config: ViewerConfig) -> bool:
        # Served on loopback, only loopback names are accepted, so that a web page elsewhere
        # cannot read the run through DNS rebinding.
        if config.allow_remote:
            return True
        host = self.headers.get("Host", "")
        name = host[1:host.find("]")] if host.startswith("[") else host.partition(":")[0]
        return is_loopback(name)

    def _send(self, body: bytes, content_type: str) -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _stream(self, viewer: ViewerService) -> None:
        """Server-sent events: one `data:` line of JSON per update, at most rate_hz per second."""
        if not viewer.stream_slots.acquire(blocking=False):
            self.send_error(HTTPStatus.SERVICE_UNAVAILABLE, f"already {viewer.config.max_clients} browsers watching")
            return
        try:
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(b"retry: 1000\n\n")
            config = viewer.config
            cursor, fleet_cursor = Cursor(), FleetCursor()
            sent_revision, sent_at, map_at, images_at = None, 0.0, 0.0, 0.0
            while not viewer.http_stop.is_set():
                now = time.monotonic()
                if viewer.revision() != sent_revision or now - sent_at >= KEEPALIVE_S:
                    sent_revision = viewer.revision()
                    state = viewer.view(cursor, include_map=now - map_at >= 1 / config.map_rate_hz,
                                        include_images=now - images_at >= 1 / config.image_rate_hz,
                                        fleet_cursor=fleet_cursor)
                    map_at = now if "map" in state else map_at
                    images_at = now if "camera" in state or "lattice" in state else images_at
                    self.wfile.write(b"data: " + viewer.encode(state) + b"\n\n")
                    self.wfile.flush()
                    sent_at = now
                viewer.http_stop.wait(1 / config.rate_hz)
        finally:
            viewer.stream_slots.release()

    def log_message(self, format: str, *args) -> None:  # noqa: A002 (http.server's signature)
        log.debug("http %s: " + format, self.address_string(), *args)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_field_flag(parser, ViewerConfig, "http", metavar="HOST:PORT")
    add_field_flag(parser, ViewerConfig, "allow_remote")
    add_field_flag(parser, ViewerConfig, "rate_hz", flag="--rate", metavar="HZ")
    add_flag(parser, FleetViewParams, "fleet", action="store_true", default=None)


def fleet_items(message: FleetUpdate | FleetSnapshot) -> tuple[list[dict], list, list]:
    """A FleetUpdate's or FleetSnapshot's robots, experiences and closures as fleet.py takes them."""
    robots = [robot.model_dump(include={"name", "joined", "joined_at", "part", "experiences"}) for robot in message.robots]
    experiences = [(e.robot, e.id, e.x, e.y) for e in message.experiences]
    links = [(link.robot, link.index, link.experience, link.matched_robot, link.matched_experience, link.fate)
             for link in message.links]
    return robots, experiences, links


def main(runtime: RuntimeConfig, args: argparse.Namespace) -> int:
    config = load_config(ViewerConfig, "viewer", config_file=args.config,
                         overrides={"http": args.http, "allow_remote": args.allow_remote, "rate_hz": args.rate_hz,
                                    "fleet": args.fleet})
    service = ViewerService(runtime, config, args.instance)
    print(f"gridslam viewer: {service.url}", flush=True)
    return service.run()
