"""The stack across hosts and from the outside: the router and the services in separate network
namespaces joined by a veth pair (test hosts of our own), and a client that knows only Zenoh and
msgpack following map/pose while a run goes on."""

import subprocess
import sys

import pytest

from tests.netutil import REPO, endpoint, free_port, port_open, veth_namespaces, wait_for

GRIDSLAM = [sys.executable, "-m", "services.cli"]
CLIENT = REPO / "examples" / "pose_client.py"


def test_external_client_follows_map_pose_during_a_run(tmp_path):
    port = free_port()
    run = subprocess.Popen(GRIDSLAM + ["run", "--source", "synthetic:0", "--preset", "synthetic", "--egomotion",
                                       "passthrough", "--n-frames", "150", "--listen", endpoint(port), "--out",
                                       str(tmp_path / "out")], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           text=True)
    try:
        wait_for(lambda: port_open(port) or run.poll() is not None, timeout=30)
        client = subprocess.run([sys.executable, str(CLIENT), "--connect", endpoint(port), "--count", "20"],
                                capture_output=True, text=True, timeout=120)
        assert client.returncode == 0, client.stderr
        lines = client.stdout.splitlines()
        assert len(lines) == 20 and any(line.startswith("map/pose seq=") for line in lines), client.stdout
        out, err = run.communicate(timeout=180)
        assert run.returncode == 0, err
    finally:
        if run.poll() is None:
            run.kill()


@pytest.fixture
def two_hosts():
    """Namespaces `router` and `robot` joined by a veth pair, 10.231.0.1 and 10.231.0.2."""
    with veth_namespaces(("gs-router", "gs-robot"), ("gsr", "gsb"), "10.231.0") as (router_ns, robot_ns, _):
        yield router_ns, robot_ns


def test_services_on_another_host_than_the_router(two_hosts, tmp_path):
    router_ns, robot_ns = two_hosts
    router = subprocess.Popen(["ip", "netns", "exec", router_ns, *GRIDSLAM, "router", "--listen", "tcp/10.231.0.1:7447"],
                              cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        done = subprocess.run(["ip", "netns", "exec", robot_ns, *GRIDSLAM, "run", "--source", "synthetic:0", "--preset",
                               "synthetic", "--egomotion", "passthrough", "--integrator", "deadreckoning", "--n-frames",
                               "60", "--connect", "tcp/10.231.0.1:7447", "--out", str(tmp_path / "out")],
                              cwd=REPO, capture_output=True, text=True, timeout=240)
        assert done.returncode == 0, done.stderr
        assert "map: frames" in done.stdout and "| 60 |" in done.stdout.replace(" ", "").replace("|60|", "| 60 |")
    finally:
        router.terminate()
        router.wait(timeout=10)
