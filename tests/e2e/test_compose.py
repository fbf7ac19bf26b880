"""docker-compose.yml and deploy/: the compose file and its overrides validate with
`docker-compose config -q` and resolve to the documented topology (a router, one container
per service reading deploy/robot.env, the dataset read-only, results on a volume, a second
robot under a profile, the estimator swapped by an override that touches nothing else, mutual
TLS with one certificate per service); the image ships what the compose file refers to; and
the same topology runs as local processes from the same deploy/robot.env.

There is no Docker engine here: `docker-compose config` needs none. The test finds
docker-compose (or `docker compose`); in CI (CI=true) or with GRIDSLAM_INSTALL_TOOLS=1 it
installs it when missing (Debian's package as root, else pip docker-compose==1.29.2 into a
cached virtualenv), and otherwise skips with the reason.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import threading
import tomllib
from pathlib import Path

import pytest
import zenoh

from services.cli.service import SERVICES
from services.common import codec, topics
from services.common.journal import read_records
from services.common.runtime import RuntimeConfig, open_session
from services.common.recovery import REPLAY_FRAMES
from services.expmap.store import parse_records
from tests.netutil import REPO, endpoint, free_port, port_open, start, stop, wait_for
from tests.tlsutil import CLIENT_MTLS, client_runtime, make_certs, tls_endpoint

COMPOSE_FILE = REPO / "docker-compose.yml"
ROBOT_ENV = REPO / "deploy" / "robot.env"
ESTIMATOR_OVERRIDE = REPO / "deploy" / "compose" / "estimator.yml"
SECURE_OVERRIDE = REPO / "deploy" / "compose" / "secure.yml"
DOCKERFILE = REPO / "deploy" / "Dockerfile"
PIPELINE = ("source", "egomotion", "gridcells", "loopclosure", "expmap", "viewer")
CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "gridslam" / "docker-compose"


def read_env_file(path: Path) -> dict[str, str]:
    """KEY=VALUE lines of an env file as docker-compose reads them (comments and blanks skipped)."""
    values = {}
    for number, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        name, sep, value = line.partition("=")
        assert sep and name.strip(), f"{path}: line {number}: expected KEY=VALUE"
        values[name.strip()] = value
    return values


# --------------------------------------------------------------------------- docker-compose itself
def _run(args: list[str], timeout: float = 300, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(args, capture_output=True, text=True, timeout=timeout, **kwargs)


def find_compose() -> list[str] | None:
    if os.environ.get("GRIDSLAM_DOCKER_COMPOSE"):
        return os.environ["GRIDSLAM_DOCKER_COMPOSE"].split()
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    if shutil.which("docker") and _run(["docker", "compose", "version"], timeout=30).returncode == 0:
        return ["docker", "compose"]
    cached = CACHE / "bin" / "docker-compose"
    return [str(cached)] if cached.is_file() else None


def install_compose() -> str:
    """Install docker-compose; returns what went wrong ('' on success)."""
    problems = []
    if hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("apt-get"):
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        install = ["apt-get", "install", "-y", "-qq", "docker-compose"]
        result = _run(install, env=env)
        if result.returncode != 0:   # a fresh machine has no package lists yet
            _run(["apt-get", "update", "-qq"], env=env)
            result = _run(install, env=env)
        if result.returncode == 0 and shutil.which("docker-compose"):
            return ""
        problems.append(f"apt-get install docker-compose: {result.stderr.strip()[-300:]}")
    # docker-compose 1.29.2 needs PyYAML < 6, whose source build fails with Cython 3.
    constraints = CACHE.parent / "docker-compose-constraints.txt"
    CACHE.parent.mkdir(parents=True, exist_ok=True)
    constraints.write_text("cython<3\n")
    result = _run([sys.executable, "-m", "venv", str(CACHE)])
    if result.returncode == 0:
        result = _run([str(CACHE / "bin" / "pip"), "install", "-q", "docker-compose==1.29.2"],
                      env={**os.environ, "PIP_CONSTRAINT": str(constraints)})
    if result.returncode == 0:
        return ""
    problems.append(f"pip install docker-compose==1.29.2: {result.stderr.strip()[-300:]}")
    return "; ".join(problems)


@pytest.fixture(scope="session")
def compose() -> list[str]:
    found = find_compose()
    if found is None:
        if not (os.environ.get("CI") or os.environ.get("GRIDSLAM_INSTALL_TOOLS")):
            pytest.skip("docker-compose not found (apt-get install docker-compose, or pip install docker-compose==1.29.2 "
                        "with cython<3 constrained); CI=true or GRIDSLAM_INSTALL_TOOLS=1 lets this test install it")
        problem = install_compose()
        found = find_compose()
        if found is None:
            pytest.skip(f"docker-compose could not be installed: {problem}")
    return found


def compose_env(**extra: str) -> dict[str, str]:
    """This process's environment without the host-side knobs the compose file reads."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("GRIDSLAM_", "COMPOSE_")) and k != "ESTIMATOR"}
    return {**env, **extra}


def compose_args(compose: list[str], files, profiles) -> list[str]:
    args = list(compose)
    for path in files:
        args += ["-f", str(path)]
    for profile in profiles:
        args += ["--profile", profile]
    return args


def yaml_to_json(text: str, compose: list[str]) -> dict:
    """Parse docker-compose's YAML with a Python that has PyYAML: ours, else docker-compose's own."""
    try:
        import yaml
        return yaml.safe_load(text)
    except ImportError:
        pass
    executable = shutil.which(compose[0]) or compose[0]
    first_line = Path(executable).read_bytes().split(b"\n", 1)[0].decode(errors="replace")
    candidates = [first_line[2:].strip().split()[0]] if first_line.startswith("#!") else []
    candidates.append("python3")
    for python in candidates:
        result = _run([python, "-c", "import json, sys, yaml; json.dump(yaml.safe_load(sys.stdin), sys.stdout)"],
                      timeout=60, input=text)
        if result.returncode == 0:
            return json.loads(result.stdout)
    pytest.skip("no Python with PyYAML to read docker-compose's resolved config")


def resolved(compose: list[str], *files: Path, profiles=("robot-b",), **env: str) -> dict:
    """The compose config as docker-compose resolves it (env files merged, overrides applied)."""
    files = files or (COMPOSE_FILE,)
    if compose[:2] == ["docker", "compose"]:
        result = _run(compose_args(compose, files, profiles) + ["config", "--format", "json"], env=compose_env(**env), cwd=REPO)
        assert result.returncode == 0, result.stderr
        return json.loads(result.stdout)
    result = _run(compose_args(compose, files, profiles) + ["config"], env=compose_env(**env), cwd=REPO)
    assert result.returncode == 0, result.stderr
    return yaml_to_json(result.stdout, compose)


def volumes_of(service: dict) -> dict[str, tuple[str, bool]]:
    """{container path: (source, read_only)} in either compose version's output format."""
    volumes = {}
    for volume in service.get("volumes", []):
        if isinstance(volume, str):
            source, target, *mode = volume.split(":")
            volumes[target] = (source, mode == ["ro"])
        else:
            volumes[volume["target"]] = (volume["source"], bool(volume.get("read_only")))
    return volumes


def ports_of(service: dict) -> set[tuple[str, int, int]]:
    """{(host address, host port, container port)} in either output format."""
    ports = set()
    for port in service.get("ports", []):
        if isinstance(port, str):
            host, published, target = port.removesuffix("/tcp").rsplit(":", 2)
            ports.add((host, int(published), int(target)))
        else:
            ports.add((port.get("host_ip", ""), int(port["published"]), int(port["target"])))
    return ports


def role_of(name: str) -> str:
    return name.removesuffix("-b")


# --------------------------------------------------------------------------- the compose files
@pytest.mark.parametrize("files, profiles, env", [
    ((COMPOSE_FILE,), (), {}),
    ((COMPOSE_FILE,), ("robot-b",), {}),
    ((COMPOSE_FILE, ESTIMATOR_OVERRIDE), ("robot-b",), {"ESTIMATOR": "scanline"}),
    ((COMPOSE_FILE, SECURE_OVERRIDE), ("robot-b",), {}),
    ((COMPOSE_FILE, SECURE_OVERRIDE), ("robot-b", "fleet"), {}),
], ids=["base", "robot-b", "estimator", "secure", "secure-fleet"])
def test_compose_config_validates(compose, files, profiles, env):
    result = _run(compose_args(compose, files, profiles) + ["config", "-q"], env=compose_env(**env), cwd=REPO)
    assert result.returncode == 0, result.stderr


def test_estimator_override_demands_an_estimator(compose):
    result = _run(compose_args(compose, (COMPOSE_FILE, ESTIMATOR_OVERRIDE), ()) + ["config", "-q"], env=compose_env(), cwd=REPO)
    assert result.returncode != 0 and "set ESTIMATOR to scanline, stereo, mono or passthrough" in result.stderr + result.stdout


def test_compose_resolves_to_the_documented_topology(compose):
    services = resolved(compose)["services"]
    robot_env = read_env_file(ROBOT_ENV)
    assert set(services) == {"router", "fleetmap", *PIPELINE, *(f"{name}-b" for name in PIPELINE)}
    fleetmap = services.pop("fleetmap")   # the fleet profile's map over every robot's (docs/fleet.md)
    assert fleetmap["profiles"] == ["fleet"] and fleetmap["command"][:2] == ["service", "fleetmap"]
    assert volumes_of(fleetmap)["/results"] == ("results", False)

    router = services["router"]
    assert router["command"] == ["router", "--listen", "tcp/0.0.0.0:7447", "--zenoh-config", "/app/deploy/router.json5"]
    assert ("127.0.0.1", 7447, 7447) in ports_of(router)
    assert router["environment"] == {"GRIDSLAM_RUNTIME_CONNECT": ""}

    for name, service in services.items():
        if name == "router":
            continue
        robot = "b" if name.endswith("-b") else "robot0"
        assert service["command"] == ["service", role_of(name)], name
        # robot.env, with robot b's name and its own folder on the results volume
        expected = {key: value.replace("/results/robot0/", f"/results/{robot}/") for key, value in robot_env.items()}
        assert service["environment"] == {**expected, "GRIDSLAM_RUNTIME_ROBOT": robot}, name
        assert "router" in service["depends_on"], name
        assert service.get("profiles", []) == (["robot-b"] if robot == "b" else []), name
        assert robot_env["GRIDSLAM_RUNTIME_CONNECT"] == "tcp/router:7447"

    for name in ("source", "source-b"):
        assert volumes_of(services[name])["/data"][1], "the dataset must be mounted read-only"
    for name in ("gridcells", "gridcells-b", "loopclosure", "loopclosure-b", "expmap", "expmap-b"):
        assert volumes_of(services[name])["/results"] == ("results", False)
    stores = [value for key, value in robot_env.items() if key.endswith(("_STORE", "_CHECKPOINT"))]
    assert stores and all(value.startswith("/results/robot0/") for value in stores)
    assert ("127.0.0.1", 8080, 8080) in ports_of(services["viewer"])
    assert ("127.0.0.1", 8081, 8080) in ports_of(services["viewer-b"])
    assert robot_env["GRIDSLAM_VIEWER_HTTP"].endswith(":8080")


def test_egomotion_scales_and_the_stateful_stages_stay_single(compose):
    """`docker-compose up --scale egomotion=N` needs a service with no fixed container name and no
    fixed host port (docs/deploy.md); the stages that keep state are not scaled (docs/pipeline.md)."""
    services = resolved(compose)["services"]
    for name in ("egomotion", "egomotion-b"):
        assert "container_name" not in services[name] and not services[name].get("ports"), name
    for name in ("gridcells", "loopclosure", "expmap"):
        assert services[name].get("deploy", {}).get("replicas", 1) == 1, name


def test_estimator_override_changes_only_the_estimator(compose):
    base = resolved(compose)["services"]
    swapped = resolved(compose, COMPOSE_FILE, ESTIMATOR_OVERRIDE, ESTIMATOR="mono")["services"]
    changed = {name for name in base if base[name] != swapped[name]}
    assert changed == {"egomotion", "egomotion-b"}
    for name in changed:
        assert swapped[name]["environment"] == {**base[name]["environment"], "GRIDSLAM_EGOMOTION_ESTIMATOR": "mono"}
        assert {k: v for k, v in swapped[name].items() if k != "environment"} == \
               {k: v for k, v in base[name].items() if k != "environment"}


def tls_paths_in(config_file: Path) -> set[str]:
    """Certificate paths a shipped Zenoh config refers to."""
    tls = json.loads(str(zenoh.Config.from_file(str(config_file))))["transport"]["link"]["tls"]
    return {value for key, value in tls.items() if isinstance(value, str) and value.startswith("/")}


def test_secure_override_gives_each_service_its_own_certificate(compose):
    services = resolved(compose, COMPOSE_FILE, SECURE_OVERRIDE)["services"]
    certs = REPO / "deploy" / "certs"
    router = services["router"]
    assert router["command"] == ["router", "--listen", "tls/0.0.0.0:7447", "--zenoh-config", "/app/deploy/acl/router.json5"]
    router_mounts = volumes_of(router)
    assert tls_paths_in(REPO / "deploy" / "acl" / "router.json5") <= set(router_mounts)
    assert Path(router_mounts["/etc/gridslam/tls/node.key"][0]) == certs / "router.key"
    for name, service in services.items():
        if name == "router":
            continue
        environment, mounts = service["environment"], volumes_of(service)
        assert environment["GRIDSLAM_RUNTIME_CONNECT"] == "tls/router:7447", name
        client_config = environment["GRIDSLAM_RUNTIME_ZENOH_CONFIG"]
        assert client_config == "/app/deploy/tls/client-mtls.json5", name
        assert tls_paths_in(REPO / client_config.removeprefix("/app/")) <= set(mounts), name
        assert Path(mounts["/etc/gridslam/tls/ca.pem"][0]) == certs / "ca.pem"
        assert Path(mounts["/etc/gridslam/tls/node.pem"][0]) == certs / f"{role_of(name)}.pem", name
        assert Path(mounts["/etc/gridslam/tls/node.key"][0]) == certs / f"{role_of(name)}.key", name
        assert all(read_only for _, read_only in (mounts[path] for path in mounts if path.startswith("/etc/gridslam"))), name


def settings_read_by(section: str) -> set[str]:
    """Upper-case field names a section's code can take from GRIDSLAM_<SECTION>_<FIELD>: the fields of
    the pydantic models its service module uses, and variables the module reads by name."""
    import importlib
    import inspect

    from pydantic import BaseModel

    module = importlib.import_module("services.common.runtime" if section == "runtime" else f"services.{section}.service")
    fields = {name.upper() for value in vars(module).values()
              if inspect.isclass(value) and issubclass(value, BaseModel) and value is not BaseModel
              for name in value.model_fields}
    source = inspect.getsource(module)
    named = set(re.findall(rf"GRIDSLAM_{section.upper()}_([A-Z0-9_]+)", source))
    if '"--preset"' in source:   # services.cli.service reads GRIDSLAM_<SERVICE>_PRESET for the flag's default
        named.add("PRESET")
    return fields | named


def test_every_setting_in_robot_env_is_read_by_its_service():
    """A misspelt or unwired variable would be ignored without a word; each one must name a
    setting its service reads."""
    unread = []
    for name in read_env_file(ROBOT_ENV):
        section = next(s for s in ("runtime", *PIPELINE) if name.startswith(f"GRIDSLAM_{s.upper()}_"))
        if name.removeprefix(f"GRIDSLAM_{section.upper()}_") not in settings_read_by(section):
            unread.append(name)
    assert not unread, f"deploy/robot.env sets variables no service reads: {unread}"


# --------------------------------------------------------------------------- the image
def test_image_holds_every_file_the_compose_files_name():
    """Every /app/deploy/... path in the compose files is in the repository and copied by the
    Dockerfile; deploy/certs (private keys) is not."""
    copied = [source for line in DOCKERFILE.read_text().splitlines() if line.startswith("COPY ")
              for source in line.split()[1:-1]]
    named = set()
    for path in (COMPOSE_FILE, ESTIMATOR_OVERRIDE, SECURE_OVERRIDE, ROBOT_ENV):
        named |= set(re.findall(r"/app/(deploy/[\w./-]+)", path.read_text()))
    assert named, "the compose files name no file of the image"
    for relative in named:
        assert (REPO / relative).is_file(), relative
        assert any(relative == source or relative.startswith(source.rstrip("/") + "/") for source in copied), relative
    assert not any(source.startswith("deploy/certs") or source in ("deploy", "deploy/", ".") for source in copied)


def test_image_install_ships_every_data_file():
    """The image installs the project as a package (not editable): every non-Python file
    under services/ and schemas/ (presets, JSON schemas, the viewer's page) must be package
    data in pyproject.toml, or the containers lack it."""
    package_data = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    shipped = {path for package, patterns in package_data.items() for pattern in patterns
               for path in (REPO / package).glob(pattern)}
    data_files = {path for package in ("services", "schemas") for path in (REPO / package).rglob("*")
                  if path.is_file() and path.suffix not in (".py", ".pyc") and "__pycache__" not in path.parts}
    missing = sorted(str(path.relative_to(REPO)) for path in data_files - shipped)
    assert not missing, f"not package data in pyproject.toml, so absent from the image: {missing}"


# --------------------------------------------------------------------------- the same topology, as processes
FRAMES = 20   # a short run (over two flow-control windows): the pipeline, not the dataset, is under test
CONTAINER_TLS = "/etc/gridslam/tls"   # where deploy/compose/secure.yml mounts each container's certificates


def local_environment(robot_env: dict[str, str], router: str, results: Path) -> dict[str, str]:
    """deploy/robot.env as the containers get it, with what only a container has replaced: the
    router's address, the results volume, and a viewer port that is free on this machine."""
    env = {name: value.replace("/results", str(results), 1) if value.startswith("/results") else value
           for name, value in robot_env.items()}
    env.update(GRIDSLAM_RUNTIME_CONNECT=router, GRIDSLAM_VIEWER_HTTP="127.0.0.1:0", GRIDSLAM_VIEWER_ALLOW_REMOTE="false",
               GRIDSLAM_SOURCE_STOP=str(FRAMES), GRIDSLAM_SOURCE_LOOP="false")
    return env


def mounted_config(shipped: Path, certs: Path, role: str, out: Path) -> Path:
    """A shipped Zenoh config as a container of `role` sees it under secure.yml: the mounted
    CA, node.pem and node.key replaced by that role's files in `certs`."""
    text = shipped.read_text()
    for mounted, local in (("ca.pem", "ca.pem"), ("node.pem", f"{role}.pem"), ("node.key", f"{role}.key")):
        text = text.replace(f"{CONTAINER_TLS}/{mounted}", str(certs / local))
    out.write_text(text)
    return out


def start_local_router(tmp_path: Path, secure: bool):
    """The router container's command on a loopback port (with `secure`, that of
    deploy/compose/secure.yml: mutual TLS and deploy/acl/router.json5), once it accepts
    connections: (router, its endpoint, an observer's runtime, own_env(env, service) giving a
    service's environment, with secure.yml's Zenoh config and the service's own certificate)."""
    port = free_port()
    if secure:
        certs = make_certs(tmp_path / "certs")
        acl = mounted_config(REPO / "deploy" / "acl" / "router.json5", certs, "router", tmp_path / "router.json5")
        router = start(["router", "--listen", tls_endpoint(port, "127.0.0.1"), "--zenoh-config", str(acl)])
        connect = tls_endpoint(port)
        observer_runtime = client_runtime(port, CLIENT_MTLS, certs, "observer")

        def own_env(env: dict[str, str], name: str) -> dict[str, str]:
            config = mounted_config(CLIENT_MTLS, certs, name, tmp_path / f"{name}.json5")
            return {**env, "GRIDSLAM_RUNTIME_ZENOH_CONFIG": str(config)}
    else:
        router = start(["router", "--listen", endpoint(port), "--zenoh-config", str(REPO / "deploy" / "router.json5")])
        connect = endpoint(port)
        observer_runtime = RuntimeConfig(connect=[connect])

        def own_env(env: dict[str, str], name: str) -> dict[str, str]:
            return dict(env)
    wait_for(lambda: port_open(port) or router.poll() is not None)
    assert router.poll() is None, router.communicate()[1]
    return router, connect, observer_runtime, own_env


@pytest.mark.parametrize("secure", [False, True], ids=["tcp", "mutual-tls-acl"])
def test_compose_topology_runs_as_local_processes(tmp_path, secure):
    """docker-compose.yml (and with `secure`, deploy/compose/secure.yml) as local processes: each
    service is `gridslam service NAME` configured by deploy/robot.env alone, all started at
    once as compose does, and every frame reaches map/pose."""
    missing = [name for name in PIPELINE if name not in SERVICES]
    if missing:
        pytest.skip(f"`gridslam service` does not offer {', '.join(missing)} yet")
    robot_env = read_env_file(ROBOT_ENV)
    robot = robot_env["GRIDSLAM_RUNTIME_ROBOT"]
    router, connect, observer_runtime, own_env = start_local_router(tmp_path, secure)
    processes = {}
    session = None
    try:
        session = open_session(observer_runtime.model_copy(update={"robot": robot}))
        poses: list[int] = []
        lock = threading.Lock()

        def on_pose(sample: zenoh.Sample) -> None:
            with lock:
                poses.append(codec.decode(sample.payload.to_bytes(), encoding=str(sample.encoding)).header.seq)
        subscriber = session.declare_subscriber(topics.key(robot, "map/pose"), on_pose)

        env = local_environment(robot_env, connect, tmp_path / "results")
        for name in PIPELINE:   # each container's command: `gridslam service NAME`, settings from the environment
            processes[name] = start(["service", name], env=own_env(env, name), cwd=tmp_path)

        def all_frames_mapped():
            crashed = {name: p.returncode for name, p in processes.items() if name != "source" and p.poll() is not None}
            assert not crashed, f"services exited: {crashed}"
            with lock:
                return set(range(FRAMES)) <= set(poses)
        wait_for(all_frames_mapped, timeout=180, period=0.5)
        assert processes["source"].wait(timeout=30) == 0   # every frame acknowledged: the source ends by itself
        subscriber.undeclare()
    finally:
        if session is not None:
            session.close()
        results = {name: stop(process) for name, process in processes.items()}
        stop(router)
    for name, (code, _, err) in results.items():
        assert code == 0, f"{name}: {err[-2000:]}"
    # The journals and the checkpoint went where robot.env puts them on the results volume.
    stores = [Path(value) for name, value in env.items() if name.endswith(("_STORE", "_CHECKPOINT"))]
    assert stores and all(path.is_relative_to(tmp_path / "results" / robot) and path.is_file() for path in stores), stores


LAP = 20   # frames per lap of the looping source in the restart test


@pytest.mark.parametrize("secure", [False, True], ids=["tcp", "mutual-tls-acl"])
def test_a_source_killed_mid_run_comes_back_where_the_pipeline_is(tmp_path, secure):
    """The compose topology as local processes, the source looping laps of LAP frames as the
    default stack does: the source killed with SIGKILL once its first frames are older than what
    the services keep to answer a re-sent frame, and started again with the same command (the
    container's restart policy), goes on where the pipeline is (no earlier frame comes again):
    poses resume and cross into the next lap, and the map holds every frame once, in order,
    stamps rising. With `secure`, through the router of deploy/compose/secure.yml (the source's
    certificate may query the services' status)."""
    robot_env = read_env_file(ROBOT_ENV)
    assert robot_env.get("GRIDSLAM_SOURCE_RESUME") == "true" and robot_env.get("GRIDSLAM_SOURCE_LOOP") == "true"
    robot = robot_env["GRIDSLAM_RUNTIME_ROBOT"]
    router, connect, observer_runtime, own_env = start_local_router(tmp_path, secure)
    env = {**local_environment(robot_env, connect, tmp_path / "results"),
           "GRIDSLAM_SOURCE_STOP": str(LAP), "GRIDSLAM_SOURCE_LOOP": "true"}
    processes, session, killed = {}, None, None
    poses: list[int] = []
    lock = threading.Lock()

    def on_pose(sample: zenoh.Sample) -> None:
        with lock:
            poses.append(codec.decode(sample.payload.to_bytes(), encoding=str(sample.encoding)).header.seq)

    def mapped_beyond(seq: int):
        def check():
            crashed = {name: p.returncode for name, p in processes.items() if p.poll() is not None}
            assert not crashed, f"services exited: {crashed}"
            with lock:
                return bool(poses) and max(poses) >= seq
        return check

    try:
        session = open_session(observer_runtime.model_copy(update={"robot": robot}))
        subscriber = session.declare_subscriber(topics.key(robot, "map/pose"), on_pose)
        for name in PIPELINE:
            processes[name] = start(["service", name], env=own_env(env, name), cwd=tmp_path)
        wait_for(mapped_beyond(REPLAY_FRAMES + 5), timeout=180, period=0.2)
        killed = processes.pop("source")
        killed.kill()
        killed.wait(timeout=10)
        with lock:
            before, restarted_at = max(poses), len(poses)
        processes["source"] = start(["service", "source"], env=own_env(env, "source"), cwd=tmp_path)
        wait_for(mapped_beyond(before + LAP), timeout=120, period=0.2)
        subscriber.undeclare()
    finally:
        if session is not None:
            session.close()
        results = {name: stop(process) for name, process in processes.items()}
        stop(router)
        if killed is not None:
            stop(killed)
    for name, (code, _, err) in results.items():
        assert code == 0, f"{name}: {err[-2000:]}"
    assert min(poses[restarted_at:]) >= before, "the restarted source sent frames the pipeline had handled"
    records, _, torn = read_records(tmp_path / "results" / robot / "experience_map.log")
    assert not torn
    steps, _ = parse_records(records[1:])   # (the first record is the map's header)
    frames = [step.frame for step in steps]
    assert frames == list(range(len(frames))) and frames[-1] >= before + LAP, "a frame is missing from the map, or there twice"
    assert all(b.stamp > a.stamp for a, b in zip(steps, steps[1:]))
