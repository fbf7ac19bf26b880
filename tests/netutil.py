"""Helpers for transport and end-to-end tests: free loopback ports, in-process sessions,
and subprocesses of the real command line that are always cleaned up."""

from __future__ import annotations

import os
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
