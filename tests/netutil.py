"""Helpers for transport and end-to-end tests: free loopback ports, in-process sessions,
and subprocesses of the real command line that are always cleaned up."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from services.common.runtime import RuntimeConfig, open_session

GRIDSLAM = [sys.executable, "-m", "services.cli"]
REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def router_session(port: int):
    return open_session(RuntimeConfig(mode="router", listen=[endpoint(port)], connect=[]))


def client_session(port: int, robot: str = "robot0"):
    return open_session(RuntimeConfig(mode="client", connect=[endpoint(port)], robot=robot))


def wait_for(predicate, timeout: float = 10.0, period: float = 0.05):
    """Poll until predicate() is truthy; returns its value, or raises AssertionError on timeout."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(period)
    raise AssertionError(f"timed out after {timeout} s waiting for {getattr(predicate, '__name__', predicate)}")


def start(args: list[str], **kwargs) -> subprocess.Popen:
    """Start `gridslam ARGS` as a subprocess of this Python."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **kwargs.pop("env", {})}
    return subprocess.Popen(GRIDSLAM + args, cwd=kwargs.pop("cwd", REPO), env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kwargs)


def port_open(port: int) -> bool:
    with socket.socket() as sock:
        return sock.connect_ex(("127.0.0.1", port)) == 0


def start_router(port: int) -> subprocess.Popen:
    """`gridslam router` on a loopback port, returned once it accepts connections."""
    router = start(["router", "--listen", endpoint(port)])
    wait_for(lambda: port_open(port) or router.poll() is not None)
    assert router.poll() is None, router.communicate()[1]
    return router


def stop(process: subprocess.Popen, timeout: float = 5.0) -> tuple[int, str, str]:
    """SIGTERM, then SIGKILL if needed; returns (exit code, stdout, stderr)."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
    try:
        out, err = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        out, err = process.communicate()
    return process.returncode, out, err


def ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True)


@contextlib.contextmanager
def veth_namespaces(names: tuple[str, str], devices: tuple[str, str], subnet: str):
    """Two network namespaces joined by a veth pair, `subnet`.1 in the first and `subnet`.2 in the
    second (a /24); yields the namespaces' names (each given a random suffix). Skips the test where
    namespaces cannot be made (not root, no iproute2); removes them afterwards."""
    import uuid

    import pytest

    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("needs root and iproute2 to make network namespaces")
    tag = uuid.uuid4().hex[:6]
    first, second = (f"{name}-{tag}" for name in names)
    try:
        ip("netns", "add", first)
        ip("netns", "add", second)
    except subprocess.CalledProcessError as error:
        pytest.skip(f"cannot make network namespaces here: {error.stderr.strip()}")
    try:
        ip("link", "add", f"{devices[0]}{tag}", "netns", first, "type", "veth", "peer", "name", f"{devices[1]}{tag}",
            "netns", second)
        for ns, dev, address in ((first, f"{devices[0]}{tag}", f"{subnet}.1/24"), (second, f"{devices[1]}{tag}", f"{subnet}.2/24")):
            ip("-n", ns, "addr", "add", address, "dev", dev)
            ip("-n", ns, "link", "set", dev, "up")
            ip("-n", ns, "link", "set", "lo", "up")
        yield first, second, f"{devices[1]}{tag}"
    finally:
        for ns in (first, second):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
