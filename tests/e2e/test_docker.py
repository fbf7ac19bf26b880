"""The image and the stacks on a real Docker engine (issue 12; docs/deploy.md, "What the tests
check"): the image builds without network from wheels prepared on the host, its build context
leaves out .git, tests, docs and keys; the default compose stack delivers map/pose to a client on
the host, `gridslam health` inside lists every service, the estimator swap recreates only
egomotion, kill -9 inside each container in turn is restarted with no frame lost in the map,
and `down -v` leaves nothing; the mutual-TLS stack serves an observer with a certificate and
refuses one without; the same stack runs on a single-node Docker Swarm.

Where no engine answers, as root the test installs Debian's docker.io (and docker-compose,
debootstrap) and starts `dockerd`, which it stops again at the end; otherwise it skips. Docker
Hub may be out of reach: without python:3.11-slim the base is the stand-in of
deploy/base-image.sh. `make docker-test` runs this file alone.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from services.common import codec, topics
from services.common.errors import ConfigError
from services.common.runtime import RuntimeConfig, open_session
from services.expmap.store import parse_records
from tests.e2e.test_compose import find_compose, install_compose
from tests.netutil import REPO, free_port, wait_for
from tests.tlsutil import CLIENT_MTLS, CLIENT_TLS, client_runtime, make_certs

pytestmark = pytest.mark.e2e

IMAGE = "gridslam:latest"                   # the image docker-compose.yml and deploy/stack.yml run
BASE = "python:3.11-slim"                   # the Dockerfile's default base
STAND_IN = "gridslam/python:3.11-bookworm"  # deploy/base-image.sh's, where Docker Hub is out of reach
PROJECT = "gridslamtest"                    # compose project and stack name: nothing of a user's is touched
# The image above its base (docs/deploy.md, "What the image weighs"): 326 MB with the map's pose
# graph (gtsam) and the place recognition's vocabulary, 449 MB in all on the stand-in's 123 MB.
MAX_OWN_LAYERS_MB = 330
PIPELINE = ("source", "egomotion", "gridcells", "loopclosure", "expmap", "viewer")


def run(args: list[str], timeout: float = 300, check: bool = True, **kwargs) -> subprocess.CompletedProcess:
    result = subprocess.run(args, capture_output=True, text=True, timeout=timeout, **kwargs)
    if check:
        assert result.returncode == 0, f"{' '.join(args)}: {result.stderr.strip()[-2000:]}"
    return result


def docker(*args: str, **kwargs) -> subprocess.CompletedProcess:
    return run(["docker", *args], **kwargs)


def engine_answers() -> bool:
    return shutil.which("docker") is not None and run(["docker", "info"], timeout=30, check=False).returncode == 0


def apt_install(*packages: str) -> None:
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    install = ["apt-get", "install", "-y", "-qq", "-o", "DPkg::Lock::Timeout=300", *packages]
    if run(install, env=env, check=False).returncode != 0:   # a fresh machine has no package lists yet
        run(["apt-get", "update", "-qq"], env=env)
        run(install, env=env)


# --------------------------------------------------------------------------- the engine and the image
@pytest.fixture(scope="module")
def engine(tmp_path_factory):
    """A Docker engine: the one that answers, else (as root) one installed and started here,
    and stopped again after the module."""
    if engine_answers():
        yield None
        return
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        pytest.skip("no Docker engine answers `docker info`, and only root with apt-get can install and start one")
    if shutil.which("dockerd") is None:
        apt_install("docker.io")
    log = open(tmp_path_factory.mktemp("dockerd") / "dockerd.log", "w")
    dockerd = subprocess.Popen(["dockerd"], stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                               start_new_session=True)
    try:
        wait_for(lambda: dockerd.poll() is not None or engine_answers(), timeout=60, period=0.5)
        assert dockerd.poll() is None, f"dockerd exited ({dockerd.returncode}); see {log.name}"
        yield dockerd
    finally:
        dockerd.terminate()
        try:
            dockerd.wait(timeout=30)
        except subprocess.TimeoutExpired:
            dockerd.kill()
            dockerd.wait()
        log.close()


@pytest.fixture(scope="module")
def compose(engine) -> list[str]:
    found = find_compose()
    if found is None and os.geteuid() == 0:
        problem = install_compose()
        found = find_compose()
        assert found is not None, f"docker-compose could not be installed: {problem}"
    if found is None:
        pytest.skip("docker-compose not found (apt-get install docker-compose)")
    return found


@pytest.fixture(scope="module")
def base_image(engine) -> str:
    """python:3.11-slim where it is there or can be pulled, else the stand-in (made once)."""
    if docker("image", "inspect", BASE, check=False).returncode == 0:
        return BASE
    if docker("pull", "-q", BASE, check=False, timeout=600).returncode == 0:
        return BASE
    if docker("image", "inspect", STAND_IN, check=False).returncode != 0:
        if shutil.which("debootstrap") is None:
            apt_install("debootstrap")
        run(["sh", str(REPO / "deploy" / "base-image.sh"), STAND_IN], timeout=600)
    return STAND_IN


@pytest.fixture(scope="module")
def image(base_image) -> str:
    """The image, built with no network from wheels prepared on the host (`make wheels`)."""
    run(["make", "-s", "-C", str(REPO), "wheels", f"PYTHON={sys.executable}"], timeout=600)
    docker("build", "-q", "--network", "none", "-f", str(REPO / "deploy" / "Dockerfile"), "--build-arg",
           f"BASE_IMAGE={base_image}", "--build-arg", "WHEELS=true", "-t", IMAGE, str(REPO), timeout=900,
           env={**os.environ, "DOCKER_BUILDKIT": "0"})
    return IMAGE


def test_build_context_leaves_out_git_tests_docs_and_keys(base_image, tmp_path):
    """The root .dockerignore, which every builder reads: a context laid out like a checkout
    with keys in it arrives without them, and with what the Dockerfile copies."""
    shutil.copy(REPO / ".dockerignore", tmp_path / ".dockerignore")
    files = [".git/HEAD", "tests/test_x.py", "docs/deploy.md", "results/latest/metrics.json", ".venv/bin/python",
             "deploy/certs/ca.key", "deploy/certs/router.pem", "deploy/tls/node.key", "services/x.key",
             "pyproject.toml", "constraints.txt", "README.md", "schemas/__init__.py", "services/__init__.py", "deploy/router.json5",
             "deploy/tls/client-mtls.json5", "deploy/wheels/README.md", "services/__pycache__/x.cpython-311.pyc"]
    for name in files:
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text("x")
    (tmp_path / "Dockerfile").write_text(f"FROM {base_image}\nCOPY . /context\n")
    tag = f"{PROJECT}-context:latest"
    docker("build", "-q", "-t", tag, str(tmp_path), env={**os.environ, "DOCKER_BUILDKIT": "0"})
    try:
        listing = docker("run", "--rm", tag, "find", "/context", "-type", "f").stdout.split()
    finally:
        docker("rmi", "-f", tag, check=False)
    arrived = {path.removeprefix("/context/") for path in listing}
    assert arrived == {"pyproject.toml", "constraints.txt", "README.md", "schemas/__init__.py", "services/__init__.py",
                       "deploy/router.json5", "deploy/tls/client-mtls.json5", "deploy/wheels/README.md"}


def test_image_runs_as_uid_10001_without_a_word_on_stderr(image):
    info = json.loads(docker("image", "inspect", image).stdout)[0]
    assert not info["Config"].get("Volumes"), "a VOLUME leaves an anonymous volume behind every container"
    assert info["Config"]["User"] == "gridslam"
    help_run = docker("run", "--rm", image, "--help")
    assert "usage: gridslam" in help_run.stdout and help_run.stderr == ""
    who = docker("run", "--rm", "--entrypoint", "sh", image, "-c", 'id; touch "$HOME/x" /results/x && echo writable')
    assert "uid=10001(gridslam) gid=10001(gridslam)" in who.stdout and "writable" in who.stdout, who.stdout + who.stderr
    own = own_layers_mb(image)
    assert own <= MAX_OWN_LAYERS_MB, f"the image adds {own:.0f} MB to its base (at most {MAX_OWN_LAYERS_MB})"


def own_layers_mb(image: str) -> float:
    """MB the image adds above its base: the layers of its own build steps."""
    rows = docker("history", "--no-trunc", "--format", "{{.CreatedBy}}\t{{.Size}}", "--human=false", image).stdout
    total = 0
    for line in rows.splitlines():
        created_by, size = line.rsplit("\t", 1)
        if created_by.strip():   # the base of `docker import` has no build step
            total += int(size)
    return total / 1e6


# --------------------------------------------------------------------------- the compose stack
class Stack:
    """A docker-compose project of this checkout's compose files, on free host ports."""

    def __init__(self, compose: list[str], project_dir: Path, files: list[Path]):
        self.router_port, self.viewer_port = free_port(), free_port()
        self.args = [*compose, "-p", PROJECT, "--project-directory", str(project_dir)]
        for path in files:
            self.args += ["-f", str(path)]
        self.env = {**{k: v for k, v in os.environ.items() if not k.startswith(("GRIDSLAM_", "COMPOSE_"))},
                    "GRIDSLAM_ROUTER_PORT": str(self.router_port), "GRIDSLAM_VIEWER_PORT": str(self.viewer_port)}

    def __call__(self, *args: str, env: dict[str, str] | None = None, **kwargs) -> subprocess.CompletedProcess:
        return run([*self.args, *args], env={**self.env, **(env or {})}, **kwargs)

    def ids(self) -> dict[str, str]:
        """{service: container id} of the running project (one `docker ps`: docker-compose 1.x starts slowly)."""
        rows = docker("ps", "--no-trunc", "--filter", f"label=com.docker.compose.project={PROJECT}",
                      "--format", '{{.Label "com.docker.compose.service"}} {{.ID}}').stdout
        return dict(line.split() for line in rows.splitlines())

    def container(self, service: str) -> str:
        return self.ids()[service]


class Poses:
    """map/pose of robot0 as a client on the host sees it (a plain Zenoh client of the router)."""

    def __init__(self, runtime: RuntimeConfig, timeout: float = 60):
        self.seqs: list[int] = []
        self.arrivals: list[float] = []
        self.lock = threading.Lock()
        deadline = time.monotonic() + timeout
        while True:   # the router's container may still be starting
            try:
                self.session = open_session(runtime)
                break
            except ConfigError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        self.subscriber = self.session.declare_subscriber(topics.key("robot0", "map/pose"), self._on_pose)

    def _on_pose(self, sample: zenoh.Sample) -> None:
        seq = codec.decode(sample.payload.to_bytes(), encoding=str(sample.encoding)).header.seq
        with self.lock:
            self.seqs.append(seq)
            self.arrivals.append(time.monotonic())

    def count(self) -> int:
        with self.lock:
            return len(self.seqs)

    def wait(self, more: int = 1, timeout: float = 60) -> None:
        """Waits for `more` poses beyond those seen so far."""
        seen = self.count()
        wait_for(lambda: self.count() >= seen + more, timeout=timeout, period=0.1)

    def longest_pause(self, since: float) -> float:
        """The longest time between two poses that arrived after `since` (or between `since` and the first)."""
        with self.lock:
            times = [since] + [t for t in self.arrivals if t > since]
        return max(b - a for a, b in zip(times, times[1:]))

    def close(self) -> None:
        self.subscriber.undeclare()
        self.session.close()


def host_runtime(port: int) -> RuntimeConfig:
    return RuntimeConfig(connect=[f"tcp/127.0.0.1:{port}"])


def journal_frames(text: str) -> list[int]:
    """Frames of an experience-map journal (its first record is the map's header; checkpoint
    records hold no frame)."""
    steps, _ = parse_records([json.loads(line.rsplit("\t", 1)[0]) for line in text.splitlines()[1:]])
    return [step.frame for step in steps]


def pid_in(container: str) -> str:
    """The gridslam process inside a container: the child of its init (docker-compose `init: true`)."""
    return docker("exec", container, "cat", "/proc/1/task/1/children").stdout.split()[0]


@pytest.fixture(scope="module")
def stack(compose, image):
    volumes_before = set(docker("volume", "ls", "-q").stdout.split())
    had_data = (REPO / "data").exists()
    stack = Stack(compose, REPO, [REPO / "docker-compose.yml"])
    stack.volumes_before = volumes_before
    stack.started = time.monotonic()
    try:
        stack("up", "-d", timeout=300)
        stack.poses = Poses(host_runtime(stack.router_port))
        yield stack
        stack.poses.close()
    finally:
        stack("down", "-v", "-t", "5", check=False)
    assert had_data or not (REPO / "data").exists(), "docker-compose up made ./data in the checkout"


def test_stack_delivers_map_poses_to_the_host_without_a_gap_or_a_warning(stack):
    stack.poses.wait(more=50, timeout=120)
    first_pose_s = stack.poses.arrivals[0] - stack.started
    with stack.poses.lock:
        seqs = list(stack.poses.seqs)
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "map/pose skipped or repeated frames"
    assert first_pose_s < 60, f"the first pose came {first_pose_s:.0f} s after `up`"
    logs = stack("logs", "--no-color").stdout
    noisy = [line for line in logs.splitlines() if " WARNING " in line or " ERROR " in line or "Traceback" in line]
    assert not noisy, "\n".join(noisy[:20])


def test_health_inside_a_container_lists_every_service(stack):
    listing = stack("exec", "-T", "gridcells", "gridslam", "health", timeout=60).stdout
    rows = {line.split()[1]: line.split() for line in listing.splitlines()[1:] if line.strip()}
    assert set(rows) == {"router", *PIPELINE}, listing
    assert all(rows[name][3] == "running" and rows[name][6] == "0" for name in PIPELINE), listing   # 0 decode errors


def test_estimator_swap_recreates_only_egomotion_and_poses_keep_flowing(stack):
    before = stack.ids()
    session = stack.poses.session
    estimators: list[str] = []
    subscriber = session.declare_subscriber(
        topics.key("robot0", "egomotion"),
        lambda sample: estimators.append(codec.decode(sample.payload.to_bytes(), encoding=str(sample.encoding)).estimator))
    try:
        stack.args += ["-f", str(REPO / "deploy" / "compose" / "estimator.yml")]
        try:
            stack("up", "-d", "--no-deps", "egomotion", env={"ESTIMATOR": "scanline"})
        finally:
            stack.args = stack.args[:-2]
        after = stack.ids()
        assert {name for name in before if before[name] != after[name]} == {"egomotion"}
        wait_for(lambda: "scanline" in estimators, timeout=60, period=0.2)
        stack.poses.wait(more=20, timeout=60)
    finally:
        subscriber.undeclare()


def test_kill_9_in_each_container_is_restarted_and_the_map_loses_no_frame(stack):
    """kill -9 of the process inside each container in turn (the source last: it resumes where the
    pipeline is): the restart policy restarts it, poses resume, and expmap's journal holds every
    frame once, in order."""
    pauses = {}
    for service in ("egomotion", "gridcells", "loopclosure", "expmap", "viewer", "router", "source"):
        container = stack.container(service)
        restarts = lambda: int(docker("inspect", "-f", "{{.RestartCount}}", container).stdout)   # noqa: E731
        before = restarts()
        stack.poses.wait(more=5)
        # 137: the container went down with its process before the exec's shell could return.
        done = docker("exec", container, "sh", "-c", f"kill -9 {pid_in(container)}", check=False)
        assert done.returncode in (0, 137), done.stderr
        killed = time.monotonic()
        wait_for(lambda: restarts() > before, timeout=30, period=0.2)
        stack.poses.wait(more=20, timeout=120)
        pauses[service] = stack.poses.longest_pause(killed)
    frames = journal_frames(stack("exec", "-T", "expmap", "cat", "/results/robot0/experience_map.log").stdout)
    assert frames == list(range(len(frames))), "a frame is missing from the map, or there twice"
    print("longest pause of map/pose after kill -9: " + ", ".join(f"{name} {pause:.1f} s" for name, pause in pauses.items())
          + f"; {len(frames)} frames in the map")


def test_down_removes_every_container_and_volume(stack):
    stack("down", "-v", "-t", "5")
    assert docker("ps", "-aq", "--filter", f"label=com.docker.compose.project={PROJECT}").stdout.strip() == ""
    assert set(docker("volume", "ls", "-q").stdout.split()) <= stack.volumes_before


# --------------------------------------------------------------------------- mutual TLS
def test_secure_stack_serves_an_observer_with_a_certificate_and_refuses_one_without(compose, image, tmp_path):
    """deploy/compose/secure.yml with certificates made by deploy/make-certs.sh, in a project
    folder of its own (the checkout's deploy/certs is left alone)."""
    project = tmp_path / "project"
    (project / "deploy").mkdir(parents=True)
    shutil.copy(REPO / "deploy" / "robot.env", project / "deploy" / "robot.env")
    certs = make_certs(project / "deploy" / "certs")
    run(["chown", "-R", "10001:10001", str(certs)])   # the containers' user reads its key (mode 0600)
    stack = Stack(compose, project, [REPO / "docker-compose.yml", REPO / "deploy" / "compose" / "secure.yml"])
    try:
        stack("up", "-d", timeout=300)
        observer = Poses(client_runtime(stack.router_port, CLIENT_MTLS, certs, "observer"))
        try:
            observer.wait(more=10, timeout=120)
        finally:
            observer.close()
        for runtime in (client_runtime(stack.router_port, CLIENT_TLS, certs, "observer"),   # no client certificate
                        host_runtime(stack.router_port)):                                   # plain TCP
            with pytest.raises(ConfigError, match="cannot open a Zenoh session"):
                open_session(runtime).close()
    finally:
        stack("down", "-v", "-t", "5", check=False)


# --------------------------------------------------------------------------- Docker Swarm
def test_swarm_stack_delivers_poses_and_shows_every_service(image, tmp_path):
    state = docker("info", "--format", "{{.Swarm.LocalNodeState}}").stdout.strip()
    if state == "inactive":
        result = docker("swarm", "init", "--advertise-addr", "127.0.0.1", check=False)
        if result.returncode != 0:
            pytest.skip(f"docker swarm init failed: {result.stderr.strip()[-300:]}")
    elif state != "active":
        pytest.skip(f"this engine's swarm is {state}")
    router_port, viewer_port = free_port(), free_port()
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("GRIDSLAM_")},
           "GRIDSLAM_ROUTER_PORT": str(router_port), "GRIDSLAM_VIEWER_PORT": str(viewer_port)}
    label = f"label=com.docker.stack.namespace={PROJECT}"
    try:
        started = time.monotonic()
        docker("stack", "deploy", "-c", str(REPO / "deploy" / "stack.yml"), PROJECT, env=env)
        poses = Poses(host_runtime(router_port), timeout=120)
        try:
            poses.wait(more=20, timeout=120)
            first_pose_s = poses.arrivals[0] - started
            health = run([sys.executable, "-m", "services.cli", "health", "-e", f"tcp/127.0.0.1:{router_port}"],
                         cwd=REPO, timeout=60).stdout
        finally:
            poses.close()
        services = {line.split()[1] for line in health.splitlines()[1:] if line.strip()}
        assert services == {"router", *PIPELINE}, health
        print(f"swarm: first pose {first_pose_s:.1f} s after `docker stack deploy`")
    finally:
        docker("stack", "rm", PROJECT, check=False)
        wait_for(lambda: docker("ps", "-aq", "--filter", label).stdout.strip() == "", timeout=60, period=0.5)
        for volume in docker("volume", "ls", "-q", "--filter", label).stdout.split():
            docker("volume", "rm", volume, check=False)
        if state == "inactive":
            docker("swarm", "leave", "--force", check=False)
            docker("network", "rm", "docker_gwbridge", check=False)
