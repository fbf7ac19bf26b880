"""An outside Foxglove client for the tests: the npm `@foxglove/ws-protocol` client (over the
`ws` package, Node.js), offering only the subprotocol `foxglove.websocket.v1`, as Lichtblick
before December 2025 and older Foxglove Studio do (tests/e2e/foxglove_client/client.js).

Its packages are installed with `npm ci` from the folder's package-lock.json into the folder's
node_modules/ on first use. Where Node.js or npm is missing, or the install fails, the tests
that need it skip, and fail in CI (CI=true)."""

from __future__ import annotations

import json
import shutil
import subprocess


from tests.extras import unavailable
from tests.netutil import REPO

FOLDER = REPO / "tests" / "e2e" / "foxglove_client"


def installed() -> str:
    """The node executable, with the client's packages installed."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        unavailable("Node.js and npm are needed for the npm @foxglove/ws-protocol client")
    if not (FOLDER / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        done = subprocess.run([npm, "ci", "--no-audit", "--no-fund", "--loglevel=error"], cwd=FOLDER,
                              capture_output=True, text=True, timeout=300)
        if done.returncode != 0:
            unavailable(f"npm ci in {FOLDER} failed: {done.stderr.strip().splitlines()[-1:]}")
    return node


def receive(url: str, quiet_ms: int = 5000, timeout_s: float = 60.0) -> dict:
    """Connect to `url`, subscribe to every channel, return what client.js printed: `subprotocol`,
    `channels`, `messages` ({topic: [[log time, base64 payload]]}) and `errors`. The client stops
    once nothing has come for `quiet_ms`: long enough that a server starved of the CPU for a moment
    by the tests beside it (a whole-suite run on 2 cores) is not taken for one that has sent all."""
    node = installed()
    done = subprocess.run([node, str(FOLDER / "client.js"), url, str(quiet_ms), str(int(timeout_s * 1000))],
                          capture_output=True, text=True, timeout=timeout_s + 30)
    assert done.stdout.strip(), f"the npm client printed nothing (exit {done.returncode}): {done.stderr[-2000:]}"
    result = json.loads(done.stdout.strip().splitlines()[-1])
    result["exit_code"] = done.returncode
    return result
