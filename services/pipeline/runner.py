"""Runs the whole stack as separate local processes around a Zenoh router on loopback (DESIGN.md,
"Runtime": the embedded default), supervises them, and evaluates the run.

Steps: router → every service → wait for their health tokens → source (last, so no frame is
published before its consumers listen) → wait until the last stage acknowledges the last frame,
restarting any service that dies → query statuses and the map → stop everything → evaluate.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, create_model

from services.common import health, topics
from services.common.config import describe_preset, is_preset_file, load_config, preset_applies
from services.common.errors import ConfigError, GridslamError
from services.common.journal import SESSION, read_records
from services.common.layout import (CONFIG, GRID_CHECKPOINT, LOGS, MAP_LOG, RUN_STATE_PATTERNS, TEMPLATE_LOG, MapReuseParams,
                                     map_files, session_base)
from services.common.run_settings import RunParams
from services.common.runtime import RuntimeConfig
from services.common.settings import config_fields, passed_on
from services.common.stages import INTEGRATORS, GridStageParams
from services.egomotion import resolve_estimator, resolve_sharding
from services.evaluation.results import results_dir, write_config
from services.evaluation.trajectory import read_tum
from services.expmap.export import read_log
from services.expmap.graph import MapParams
from services.loopclosure.keyframes import check_file as check_keyframes
from services.loopclosure.service import LoopClosureConfig
from services.pipeline.assumptions import assess
from services.pipeline.recorder import Recorder
from services.pipeline.report import evaluate, write_report
from services.ros.foxglove import check_available as check_foxglove_available
from services.ros.mcap_export import write_after_run
from services.ros2wire.rmw_zenoh import GraphParams
from services.source.service import SourceConfig
from services.source.spec import BagParams, bag_settings, open_source

log = logging.getLogger(__name__)

STARTUP_TIMEOUT_S = 120.0   # services settle networks and load models before their token appears
STOP_TIMEOUT_S = 5.0
RESEND_AFTER_S = 2.0        # a stage restarted by the runner is back within this; then frames in flight go again
# With N egomotion instances the source keeps at least N + SHARDED_SPARE_BLOCKS blocks of frames
# in flight: one for each instance to work on, and the next one already sent (docs/pipeline.md).
SHARDED_SPARE_BLOCKS = 1
# A child that exits this many times in a row with no frame completed in between fails for a
# reason a restart does not cure (a full disk, a bad file): the run stops and quotes it.
RESTARTS_WITHOUT_PROGRESS = 3
TAIL_LINES = 20             # last lines of each child's output kept in memory
FLEET_WAIT_S = 60.0         # a fleet member at its end: how long it waits for the fleet map to hold its whole map
LIVENESS_CHECK_S = 2.0      # while no frame completes, how often the stages' health tokens are checked


ASSUMED = "assumed"   # config.json's entry of what the run assumed (assumptions.py), beside RunConfig's fields


class RunError(GridslamError):
    """The run could not start or complete (the message says which service and where its log is)."""


class _RunFields(BaseModel):
    """A whole-stack run (`gridslam run`); written to config.json in the results folder."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    integrator: Literal[INTEGRATORS] = Field("grid", description="Path integrator.")
    origin: int | None = Field(None, ge=0, description="The frame whose pose is the ground truth's origin (default: the "
                                                       "run's first; a fleet's robots: the first robot's first frame).")
    world: dict[str, int | float | bool | str] = Field(
        default_factory=dict, description="Synthetic world settings for the source (--laps, --world KEY=VALUE), over the "
                                          "preset's and the config file's [source] keys.")


# The run's own settings (RunParams: --source, --stride, --egomotion-instances, ...) and the ones
# it passes on to a service, declared once with it; None: the service's. The grid-cell stage's
# choices (GridStageParams: --decoder, --step-source, --modules, --heading) and the ROS 2 graph
# settings of the ros2 service and of a ros2: source (GraphParams: --ros-domain-id,
# --ros-namespace, --ros-distro, --ros2-keys).
_GRID_STAGE = config_fields(GridStageParams, optional=True)
_MAP_MODEL = config_fields(MapParams, optional=True)
RunConfig = create_model("RunConfig", __base__=_RunFields, __doc__=_RunFields.__doc__, **config_fields(RunParams),
                         decoder=_GRID_STAGE["decoder"], step_source=_GRID_STAGE["step"], modules=_GRID_STAGE["modules"],
                         heading=_GRID_STAGE["heading"], closure=_MAP_MODEL["closure"],
                         map_optimizer=_MAP_MODEL["optimizer"], **config_fields(MapReuseParams),
                         **passed_on(SourceConfig, "fov"), **config_fields(BagParams),
                         **passed_on(LoopClosureConfig, "place_recognition", "fleet"),
                         **config_fields(GraphParams, optional=True))


@dataclass
class Child:
    name: str
    args: list[str]
    log_path: Path
    process: subprocess.Popen | None = None
    restarts: int = 0
    seen: bool = False                # its health token was seen since its last start
    exits_without_progress: int = 0   # exits since a frame last completed
    announced: str | None = None      # what it printed on its `gridslam <name>: ...` line: where a server serves
                                      # (`gridslam viewer: http://...`), that a fleet member is parked
    tail: collections.deque = field(default_factory=lambda: collections.deque(maxlen=TAIL_LINES))
    readers: list[threading.Thread] = field(default_factory=list)


@dataclass
class Supervisor:
    """Starts, watches, restarts and stops the run's processes (subprocesses: never a fork of a
    process that has a Zenoh session open).

    A child's output comes through a pipe: a thread copies it to the child's log file and keeps
    its last lines, so the runner can quote why a child failed even when the log cannot be
    written (a full disk)."""

    log_dir: Path
    children: dict[str, Child] = field(default_factory=dict)

    def start(self, name: str, args: list[str], module: str = "services.cli") -> Child:
        """Start ``python -m module args`` (the gridslam command line unless told otherwise)."""
        child = self.children.get(name) or Child(name, args, self.log_dir / f"{name}.log")
        child.args = args
        self.children[name] = child
        # One BLAS and one OpenCV thread per service (unless set): the services are single-threaded
        # pipeline stages sharing the cores. Spinning BLAS threads on busy cores slow a 128×128 SVD
        # a hundredfold; OpenCV's threads cost the stereo estimator 2–4 ms more CPU a frame on
        # NuBot (docs/benchmarks.md), CPU the other stages need.
        env = {**os.environ, **{name: os.environ.get(name, "1") for name in ("OPENBLAS_NUM_THREADS", "OPENCV_FOR_THREADS_NUM")}}
        child.process = subprocess.Popen([sys.executable, "-m", module, *args], stdout=subprocess.PIPE,
                                         stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        child.seen = False
        reader = threading.Thread(target=self._copy_output, args=(child, child.process.stdout), daemon=True,
                                  name=f"{name} output")
        reader.start()
        child.readers = [r for r in child.readers if r.is_alive()] + [reader]
        return child

    @staticmethod
    def _copy_output(child: Child, stream) -> None:
        try:
            log_file = open(child.log_path, "ab")
        except OSError as error:
            log.warning("%s: cannot write its log %s (%s)", child.name, child.log_path, error.strerror)
            log_file = None
        with stream:
            announcement = f"gridslam {child.name.partition('-')[0]}: ".encode()
            for line in stream:
                child.tail.append(line.decode(errors="replace").rstrip())
                if line.startswith(announcement):   # a server saying where it serves, a fleet member that it is parked
                    child.announced = line[len(announcement):].decode(errors="replace").strip()
                if log_file is None:
                    continue
                try:
                    log_file.write(line)
                    log_file.flush()
                except OSError as error:
                    log.warning("%s: cannot write its log %s (%s)", child.name, child.log_path, error.strerror)
                    log_file = None   # the last lines are still kept in memory
        if log_file is not None:
            try:
                log_file.close()
            except OSError:
                pass

    def exited(self, name: str) -> int | None:
        child = self.children[name]
        return child.process.poll() if child.process else None

    def restart(self, name: str, args: list[str] | None = None) -> None:
        child = self.children[name]
        child.exits_without_progress += 1
        if child.exits_without_progress > RESTARTS_WITHOUT_PROGRESS:
            raise RunError(f"{name} exited {child.exits_without_progress} times (last code {child.process.returncode}) "
                           f"with no frame completed in between: {self.log_tail(name, 1) or 'no output'} "
                           f"(log: {child.log_path})")
        child.restarts += 1
        log.warning("%s exited with code %s; restart %d", name, child.process.returncode, child.restarts)
        self.start(name, args or child.args)

    def wait_until(self, name: str, predicate, what: str) -> None:
        """Wait until ``predicate()`` holds for the child ``name``'s start-up; RunError when it exits
        first, or after STARTUP_TIMEOUT_S (``what`` it did not do)."""
        child = self.children[name]
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not predicate():
            code = self.exited(name)
            if code is not None:
                raise RunError(f"{name} exited at start-up (code {code}): {self.log_tail(name)} (log: {child.log_path})")
            if time.monotonic() > deadline:
                raise RunError(f"{name} did not {what} within {STARTUP_TIMEOUT_S:.0f} s (log: {child.log_path})")
            time.sleep(0.05)

    def address(self, name: str) -> str:
        """The address a server child printed (`gridslam viewer: URL`), once it has."""
        child = self.children[name]
        self.wait_until(name, lambda: child.announced is not None, "say where it serves")
        return child.announced

    def progressed(self) -> None:
        """A frame completed: the restarts so far did their job."""
        for child in self.children.values():
            child.exits_without_progress = 0

    def log_tail(self, name: str, lines: int = 5) -> str:
        child = self.children[name]
        for reader in child.readers:   # the child has exited: let its last lines arrive
            reader.join(timeout=1.0)
        return " | ".join(list(child.tail)[-lines:])

    def newest_warning(self, names: list[str]) -> str | None:
        """The message of the newest WARNING or ERROR line in the named children's last lines, led
        by the child's name (the lines start with their time, so the newest sorts last), or None."""
        found = [(line, name) for name in names if name in self.children
                 for line in list(self.children[name].tail) if " WARNING " in line or " ERROR " in line]
        if not found:
            return None
        line, name = max(found)
        message = line.split(" ", 4)[-1]   # after the date, time, level and logger
        return message if message.startswith(f"{name}:") else f"{name}: {message}"

    def stop(self, names: list[str]) -> None:
        """SIGTERM the named children together, SIGKILL what is left after STOP_TIMEOUT_S."""
        running = [self.children[n] for n in names if n in self.children and self.children[n].process.poll() is None]
        for child in running:
            child.process.send_signal(signal.SIGTERM)
            child.process.send_signal(signal.SIGCONT)   # a stopped child must run to see the SIGTERM
        deadline = time.monotonic() + STOP_TIMEOUT_S
        for child in running:
            try:
                child.process.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop within %.0f s; killed", child.name, STOP_TIMEOUT_S)
                child.process.kill()
                child.process.wait()
        for name in names:
            for reader in self.children[name].readers if name in self.children else ():
                reader.join(timeout=1.0)


def endpoint_port(endpoint: str) -> tuple[str, int]:
    try:
        protocol, address = endpoint.split("/", 1)
        host, port = address.rsplit(":", 1)
        return host.strip("[]"), int(port)
    except ValueError:
        raise ConfigError(f"listen endpoint {endpoint!r} is not PROTOCOL/HOST:PORT") from None


def check_port_free(endpoint: str) -> None:
    host, port = endpoint_port(endpoint)
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError:
            raise ConfigError(f"{endpoint} is in use (another gridslam run?); choose another with --listen") from None


def wait_port_open(endpoint: str, process: subprocess.Popen, timeout: float = 15.0) -> None:
    host, port = endpoint_port(endpoint)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and process.poll() is None:
        with socket.socket() as sock:
            if sock.connect_ex((host, port)) == 0:
                return
        time.sleep(0.05)
    raise RunError(f"the router did not start listening on {endpoint}")


def router_endpoint(config: RunConfig) -> str:
    """Where the run's services connect: the router it started, or the one it was given."""
    return config.connect or config.listen


def egomotion_children(config: RunConfig) -> list[str]:
    """The run's egomotion processes: egomotion, egomotion-2, ... (also their instance names)."""
    return ["egomotion"] + [f"egomotion-{index}" for index in range(2, config.egomotion_instances + 1)]


def shard_block(config: RunConfig) -> int | None:
    """Frames per block the run's egomotion instances run their estimator in, resolved as each
    of them resolves it (services.egomotion.resolve_sharding: the estimator the preset, the
    config file or the flags name, [egomotion] shard_block, GRIDSLAM_EGOMOTION_SHARD_BLOCK);
    None with one instance, which runs it frame after frame."""
    preset = config.preset if config.preset and preset_applies("egomotion", config.preset) else None
    estimator, _ = resolve_estimator(config.egomotion, preset, config.config_file, config.camera_height)
    return resolve_sharding(estimator, config.egomotion_instances, config_file=config.config_file)[1]


def source_window(config: RunConfig) -> int:
    """Frames in flight: the configured window, and with several egomotion instances enough for
    each to have a block of frames and the next already sent."""
    block = shard_block(config)
    if block is None:
        return config.window
    return max(config.window, (config.egomotion_instances + SHARDED_SPARE_BLOCKS) * block)


def service_args(config: RunConfig, child: str, folder: Path) -> list[str]:
    """`gridslam service NAME ...` arguments of one process of the run (`child`: its name, also its
    instance name; egomotion-2 is a second egomotion)."""
    name = child.partition("-")[0]
    args = ["service", name, "-e", router_endpoint(config), "--robot", config.robot, "--instance", child]
    if config.config_file is not None:
        args += ["--config", str(config.config_file)]
    if config.preset and preset_applies(name, config.preset):
        args += ["--preset", config.preset]
    if name == "egomotion":   # each instance is told how many share the frames (one: frame after frame)
        args += ["--instances", str(config.egomotion_instances)]
    if name == "egomotion" and config.egomotion:
        args += ["--estimator", config.egomotion]
    if name == "egomotion" and config.camera_height:
        args += ["--camera-height", str(config.camera_height)]
    if name == "gridcells":
        args += ["--integrator", config.integrator, "--checkpoint", str(folder / GRID_CHECKPOINT)]
        args += ["--decoder", config.decoder] if config.decoder else []
        args += ["--step-source", config.step_source] if config.step_source else []
        args += ["--modules", str(config.modules)] if config.modules else []
        args += ["--heading", config.heading] if config.heading else []
    if name == "viewer":
        args += ["--http", config.view]
    if name == "foxglove":
        args += ["--port", str(config.foxglove)]
    if name == "ros2":
        args += graph_args(config)
    if name == "loopclosure":
        args += ["--store", str(folder / TEMPLATE_LOG)] + (["--fleet"] if config.fleet else [])
        args += ["--place-recognition", config.place_recognition] if config.place_recognition else []
    if name == "expmap":
        args += ["--store", str(folder / MAP_LOG), "--out", str(folder)]
        args += ["--map-optimizer", config.map_optimizer] if config.map_optimizer else []
    if name in ("loopclosure", "expmap") and config.closure:
        args += ["--closure", config.closure]
    if name in ("loopclosure", "expmap") and config.map is not None:
        args += ["--map", str(config.map)] + (["--localize"] if config.localize else [])
    return args


def graph_args(config: RunConfig) -> list[str]:
    """The ROS 2 graph flags given to the run, for the ros2 service and a ros2: source."""
    args = []
    for name in (f.name for f in dataclasses.fields(GraphParams)):
        value = getattr(config, name)
        args += [f"--{name.replace('_', '-')}", str(value)] if value is not None else []
    return args


def source_args(config: RunConfig, start: int, ack_topic: str) -> list[str]:
    stop = config.start + config.n_frames * config.step if config.n_frames else None
    args = ["service", "source", "-e", router_endpoint(config), "--robot", config.robot, "--instance", "source",
            "--source", config.source, "--start", str(start), "--origin", str(origin_of(config)), "--stride", str(config.step),
            "--window", str(source_window(config)), "--ack-topic", ack_topic, "--resend-after", str(RESEND_AFTER_S)]
    if config.egomotion_instances > 1:
        # Instances work in parallel only on blocks already sent: a window fitted to one frame's
        # latency would leave all but one idle.
        args.append("--no-adaptive-window")
    if config.config_file is not None:
        args += ["--config", str(config.config_file)]
    if config.preset:
        args += ["--preset", config.preset]
    if config.calibration is not None:
        args += ["--calibration", str(config.calibration)]
    if config.fov is not None:
        args += ["--fov", str(config.fov)]
    for key, value in config.world.items():
        args += ["--world", f"{key}={str(value).lower() if isinstance(value, bool) else value}"]
    for key, value in bag_settings(config).items():
        args += [f"--{key.replace('_', '-')}", str(value)] if value is not None else []
    if config.source.startswith("ros2:"):
        args += graph_args(config)
    return args + (["--stop", str(stop)] if stop is not None else [])


def origin_of(config: RunConfig) -> int:
    """The frame whose pose is the ground truth's origin: the run's first, or on a saved map of
    the same source the first of the run that made the map (so that its frame is the truth's)."""
    if config.origin is not None:
        return config.origin
    if config.map is not None:
        try:
            saved = json.loads((config.map / CONFIG).read_text())
        except (OSError, ValueError):
            return config.start
        if saved.get("source") == config.source and isinstance(saved.get("start"), int):
            return saved["start"]
    return config.start


def check_saved_map(config: RunConfig) -> None:
    """A run on a saved map fails at once, in one line, when the map is not there."""
    if config.localize and config.map is None:
        raise ConfigError("--localize needs a saved map to localise on: --map DIR")
    if config.map is None:
        return
    if not config.mapping:
        raise ConfigError("--map needs the map stage (drop --no-mapping)")
    if not config.map.is_dir():
        raise ConfigError(f"{config.map}: no such results folder (--map DIR: the folder of an earlier run)")
    files = map_files(config.map)
    missing = [path.name for path in files.values() if not path.is_file()]
    if missing:
        raise ConfigError(f"{config.map}: no saved map there (missing {', '.join(missing)})")
    # Damage anywhere: one line naming the file and the place, before anything starts (the
    # services check the rest — that the map was made with this run's settings — at start-up).
    read_records(files["places"])
    read_records(files["map"])
    check_keyframes(files["keyframes"])


def source_settings(config: RunConfig) -> SourceConfig:
    """The source's settings as its service will resolve them: the config file's [source] under
    the run's flags."""
    return load_config(SourceConfig, "source", config_file=config.config_file, overrides={
        "source": config.source, "preset": config.preset, "calibration": config.calibration, "fov": config.fov,
        **config.world,
        **bag_settings(config)})


def log_preset(config: RunConfig, services: list[str]) -> None:
    """For a preset file, one line saying which services take keys from it and which stay on a
    preset (a warning when some run on their defaults). Checks the file first."""
    if not config.preset or not is_preset_file(config.preset):
        return
    line = describe_preset(config.preset, services)
    if all(preset_applies(name, config.preset) for name in services):
        log.info("%s", line)
    else:
        log.warning("%s", line)


SERVERS = ("viewer", "foxglove")   # observers a user connects to: they announce an address


@dataclass
class Serving:
    """A finished run's observers (the viewer, the Foxglove server, the ros2 node) and its router,
    kept running so that a browser or Foxglove can still connect, until `wait()` returns."""

    supervisor: Supervisor
    names: list[str]

    @property
    def addresses(self) -> dict[str, str]:
        return {name: self.supervisor.children[name].announced for name in SERVERS
                if name in self.names and self.supervisor.children[name].announced}

    def wait(self, stop_event: threading.Event | None = None) -> None:
        """Until Ctrl-C (SIGINT), SIGTERM, `stop_event`, or every server has exited; then stop them.

        The signals set `stop_event` rather than raise KeyboardInterrupt anywhere in the loop: one
        raised inside `Popen.poll()` just after it took the child's wait lock leaves the lock held,
        and stopping that child then waits on it for ever (the served run that once ignored Ctrl-C)."""
        stop_event = stop_event or threading.Event()
        previous = {}
        if threading.current_thread() is threading.main_thread():
            previous = {signum: signal.signal(signum, lambda *_: stop_event.set()) for signum in (signal.SIGINT, signal.SIGTERM)}
        try:
            while not stop_event.wait(0.2):
                if all(self.supervisor.exited(name) is not None for name in self.names if name in SERVERS):
                    log.warning("the run's viewer and Foxglove server have exited")
                    break
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)
            self.close()

    def close(self) -> None:
        self.supervisor.stop(self.names)
        self.supervisor.stop(["router"])


@dataclass
class RunResult:
    folder: Path
    metrics: dict
    serving: Serving | None = None   # with run_pipeline(serve=True): the finished run's servers, still running


def run_pipeline(config: RunConfig, out: Path | None = None, progress=None, stop_event: threading.Event | None = None,
                 overwrite: bool = False, announce=None, serve: bool = False, park=None) -> RunResult:
    """Run the whole stack on `config.source`, write the results folder, return its metrics.

    `progress(done, total)` is called about five times a second; `stop_event` ends the run early;
    `announce(line)` is given the lines saying what the run assumes (estimator, camera, scale)
    before it starts, and the viewer's and the Foxglove server's addresses. A run whose
    estimator cannot work on its source fails before anything starts (assumptions.StageInputError).
    With `serve`, a run that ends by itself (its source finished) and has a viewer or a Foxglove
    server leaves them (and the router, the ros2 node) running: RunResult.serving, whose
    `wait()` the caller calls once it has shown the results.
    A folder that holds an earlier run is refused, or cleared first with `overwrite`: its
    services would resume that run's state instead of starting afresh.
    `park()`, given, is called once the source has finished (a fleet member's: once the fleet map
    holds its map) with every stage still up; the run ends when it returns. A fleet run parks its
    robots so that one that has finished still gives its places to a robot that joins later."""
    stop_event = stop_event or threading.Event()
    check_saved_map(config)
    if config.connect is None:
        check_port_free(config.listen)
    if config.foxglove is not None:   # fail now, in one line, rather than lose the live view quietly
        check_foxglove_available()
        if config.foxglove:
            check_port_free(f"tcp/127.0.0.1:{config.foxglove}")
    stop = config.start + config.n_frames * config.step if config.n_frames else None
    stages = egomotion_children(config) + ["gridcells"] + (["loopclosure", "expmap"] if config.mapping else [])
    log_preset(config, ["source", *dict.fromkeys(child.partition("-")[0] for child in stages)])
    settings = source_settings(config)
    frames = open_source(config.source, start=config.start, stop=stop, step=config.step, preset=settings.preset,
                         calibration=settings.calibration, world=settings.world(), topics=bag_settings(settings),
                         fov=settings.fov)
    total = None if getattr(frames, "live", False) else len(frames)
    assumed = assess(config.egomotion, config.preset, config.config_file, config.camera_height, config.source, frames)
    folder = results_dir(out)
    clear_previous_run(folder, overwrite)
    write_config(folder / CONFIG, {**config.model_dump(mode="json"), ASSUMED: assumed.record()})
    for line in assumed.lines():
        (announce or log.info)(line)
    (folder / LOGS).mkdir(exist_ok=True)
    ack_topic = "map/pose" if config.mapping else "grid/pose"
    supervisor = Supervisor(folder / LOGS)
    started = time.monotonic()
    kept: list[str] = []   # children that go on serving the finished run
    observers = (["viewer"] if config.view else []) + (["foxglove"] if config.foxglove is not None else []) + \
        (["ros2"] if config.ros2 else [])
    try:
        if config.connect is None:
            router = supervisor.start("router", ["router", "--listen", config.listen])
            wait_port_open(config.listen, router.process)
        for name in stages + observers:
            supervisor.start(name, service_args(config, name, folder))
        runtime = RuntimeConfig(connect=[router_endpoint(config)], robot=config.robot)
        with Recorder(runtime, camera_images=config.mcap) as recorder:
            _wait_for_services(supervisor, recorder, stages)
            for name in (name for name in observers if name in SERVERS):
                (announce or log.info)(f"{name}: {supervisor.address(name)}")
            supervisor.start("source", source_args(config, config.start, ack_topic))
            completed = _supervise(config, supervisor, recorder, stages, ack_topic, total, progress, stop_event)
            if completed and config.fleet:
                _wait_for_fleet_map(recorder.session, config.robot, stop_event)
            wall_time = time.monotonic() - started
            if completed and park is not None:
                park()
            statuses = recorder.statuses()
            recording = recorder.recording
        if serve and completed and any(name in SERVERS for name in observers):
            kept = observers
    finally:
        # The stages first (expmap sends the map as it ends), then the observers that are not kept.
        supervisor.stop([n for n in supervisor.children if n not in ("router", *observers)])
        supervisor.stop([n for n in observers if n not in kept])
        if not kept:
            supervisor.stop(["router"])
    serving = Serving(supervisor, kept) if kept else None
    try:
        return RunResult(folder, _write_results(folder, config, supervisor, recording, statuses, total, wall_time), serving)
    except BaseException:
        if serving is not None:   # the results could not be written: nothing is left to serve
            serving.close()
        raise


def _write_results(folder, config, supervisor, recording, statuses, total, wall_time) -> dict:
    """Evaluate the finished run and write its results folder; its metrics."""
    if (folder / MAP_LOG).exists():
        final_map(folder, config, recording)
    restarts = {name: child.restarts for name, child in supervisor.children.items() if child.restarts}
    result, trajs = evaluate(recording, statuses, restarts, total, wall_time)
    if config.mcap:
        result["summary"]["run_mcap"] = write_after_run(folder, recording, trajs, config)
    write_report(folder, recording, result, trajs)
    return result


def final_map(folder: Path, config: RunConfig, recording) -> None:
    """This run's frames placed on the final map, and the map's decisions on its closures, into
    the recording; on a saved map, only this session's frames (a localisation's: the poses it
    published, since it changes no map), and the saved sessions' true positions to judge them."""
    map_log = read_log(folder / MAP_LOG)
    experience_map = map_log.rebuild()
    base = session_base(map_log.sessions[-1][1][SESSION]) if map_log.sessions else 0
    recording.frame_base = base
    whole_map = {frame: (x, y, heading) for frame, x, y, heading in experience_map.trajectory()}
    recording.final_map = {frame - base: pose for frame, pose in whole_map.items() if frame >= base}
    if experience_map.localizer is not None:   # a localisation's frames, from when they are in the map's frame
        recording.final_map = {seq: pose[:3] for seq, pose in recording.map_poses.items() if pose[4]}
    elif base:                                 # a later session: the map of every session, to score
        recording.whole_map = whole_map
    recording.map_decisions = [decision for decision in experience_map.decisions if decision[0] >= base]
    if config.map is not None and (config.map / "groundtruth.tum").is_file():
        truth = read_tum(config.map / "groundtruth.tum")
        at_stamp = {round(stamp, 6): tuple(position[:2]) for stamp, position in zip(truth.stamps, truth.positions)}
        recording.saved_truth = {step.frame: at_stamp[round(step.stamp, 6)] for step in map_log.steps
                                 if step.frame < base and round(step.stamp, 6) in at_stamp}


def clear_previous_run(folder: Path, overwrite: bool) -> None:
    """Refuse a results folder that holds an earlier run's state, or remove that state (`overwrite`)."""
    previous = sorted(path for pattern in RUN_STATE_PATTERNS for path in folder.glob(pattern) if path.is_file())
    if not previous:
        return
    if not overwrite:
        names = ", ".join(str(path.relative_to(folder)) for path in previous[:3]) + (", …" if len(previous) > 3 else "")
        raise RunError(f"{folder} already holds a run ({names}): give another --out, or --overwrite to replace it")
    for path in previous:
        try:
            path.unlink()
        except OSError as error:
            raise RunError(f"{path}: cannot remove the earlier run's file ({error.strerror or error})") from None


def _wait_for_services(supervisor: Supervisor, recorder: Recorder, stages: list[str]) -> None:
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while True:
        for name in stages:
            code = supervisor.exited(name)
            if code is not None and code < 0:   # killed by a signal: restarted, as in the run
                supervisor.restart(name)
            elif code is not None:              # an error of its own (a bad setting): restarting cures nothing
                raise RunError(f"service {name} exited at start-up (code {code}): "
                               f"{supervisor.log_tail(name)} (log: {supervisor.children[name].log_path})")
        live = recorder.live_instances()   # every process is started with its name as its instance
        missing = set(stages) - live
        if not missing:
            for name in stages:
                supervisor.children[name].seen = True
            return
        if time.monotonic() > deadline:
            raise RunError(f"services {sorted(missing)} did not come up within {STARTUP_TIMEOUT_S:.0f} s")
        time.sleep(0.1)


def _wait_for_fleet_map(session, robot: str, stop_event: threading.Event) -> None:
    """A fleet member at its last frame: until a live fleet map holds every experience of the
    robot's map (it takes a part it missed from the map's snapshot, which needs the robot's expmap
    up), at most FLEET_WAIT_S; at once when no fleet map is alive (the robot never waits for one
    that is down). A fleet map that is alive but slow to answer (busy catching up) is waited for."""
    deadline = time.monotonic() + FLEET_WAIT_S
    while not stop_event.is_set() and time.monotonic() < deadline:
        if not any(service == "fleetmap" for _, service, _ in health.live_services(session, topics.FLEET, timeout=1.0)):
            return
        own = [s.extra.get("experiences") for s in health.statuses(session, robot, timeout=1.0) if s.service == "expmap"]
        fleet = [s.extra.get(f"experiences_{robot}", 0) for s in health.statuses(session, topics.FLEET, timeout=2.0)
                 if s.service == "fleetmap"]
        if own and fleet and max(fleet) >= own[0]:
            return
        time.sleep(0.5)
    log.warning("the fleet map does not hold all of robot %s's map after %.0f s", robot, FLEET_WAIT_S)


def _supervise(config, supervisor, recorder, stages, ack_topic, total, progress, stop_event) -> bool:
    """Until the source has finished (True) or `stop_event` is set (False)."""
    last_done, last_change = -1, time.monotonic()
    last_liveness_check, missed, silent = 0.0, set(), set()
    while not stop_event.is_set():
        done = recorder.count(ack_topic)
        now = time.monotonic()
        if done != last_done:
            last_done, last_change = done, now
            supervisor.progressed()
        if progress is not None:
            progress(done, total)
        code = supervisor.exited("source")
        acked = recorder.last_seq(ack_topic)
        if code == 0:   # the source exits 0 once its last frame is acknowledged
            return True
        if code is not None:
            # Resume at the last acknowledged frame: the frames in flight are sent again, after
            # one that every stage has handled (stale for them; it primes a restarted estimator).
            resume = config.start if acked is None else acked
            supervisor.restart("source", source_args(config, resume, ack_topic))
        for name in stages:
            if supervisor.exited(name) is not None:
                supervisor.restart(name)
        if "router" in supervisor.children and supervisor.exited("router") is not None:
            supervisor.restart("router")
        if now - last_change > LIVENESS_CHECK_S and now - last_liveness_check > LIVENESS_CHECK_S:
            # No progress: say which running stage left the network (its lease expired: stopped,
            # hung, or cut off). It may come back (SIGCONT, network healed) and the run resumes.
            last_liveness_check = now
            live = recorder.live_instances()
            children = [supervisor.children[name] for name in ["source", *stages]]
            for child in children:
                child.seen = child.seen or child.name in live
            # A child not seen since it (re)started is still starting; with no router, no token
            # is in sight at all.
            absent = {c.name for c in children if c.seen and c.name not in live and c.process.poll() is None} \
                if live else set()
            gone, missed = absent & missed, absent   # absent from two checks in a row: not a late reply
            for name in sorted(gone - silent):
                log.warning("%s left the network although its process runs (stopped or hung?); waiting up to "
                            "%.0f s for it", name, config.stall_timeout)
            for name in sorted(silent - gone):
                log.warning("%s is back on the network", name)
            silent = gone
        if now - last_change > config.stall_timeout:
            note = f"; not on the network although running (stopped or hung?): {', '.join(sorted(silent))}" if silent else ""
            warning = supervisor.newest_warning(["source", *stages])
            note += f"; last warning: {warning}" if warning else ""
            raise RunError(f"no frame completed for {config.stall_timeout:.0f} s (last acknowledged: {acked}){note}; "
                           f"see the logs in {supervisor.log_dir}")
        time.sleep(0.2)
    return False
