"""Headless Chromium for the end-to-end tests, driven through chromedriver's W3C WebDriver HTTP
API with urllib (Debian's packages chromium and chromium-driver; installed with apt-get when the
tests run as root and they are missing). Where they cannot be had the browser tests skip, and
fail in CI (CI=true), where they are part of what is tested."""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import urllib.error
import urllib.request
from pathlib import Path


from tests.extras import unavailable
from tests.netutil import free_port, port_open, stop, wait_for

# The flags headless Chromium needs on these machines: no sandbox as root, no GPU, and no
# background networking (the closed network refuses Chromium's own connections).
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--disable-dev-shm-usage", "--hide-scrollbars", "--window-size=1400,900"]


def chromium_and_driver() -> tuple[str, str]:
    """Paths of chromium and chromedriver; installs the Debian packages when root, else skips
    (fails in CI)."""
    found = shutil.which("chromium"), shutil.which("chromedriver")
    if all(found):
        return found
    if os.geteuid() != 0 or not shutil.which("apt-get"):
        unavailable("headless Chromium is absent (Debian packages chromium and chromium-driver) and cannot be "
                     "installed here (needs root and apt-get)")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for command in (["apt-get", "update"], ["apt-get", "install", "-y", "--no-install-recommends", "chromium", "chromium-driver"]):
        result = subprocess.run(command, env=env, capture_output=True, text=True, timeout=900)
        if result.returncode != 0:
            unavailable(f"could not install Chromium: {' '.join(command)} failed: {result.stderr.strip().splitlines()[-1:]}")
    found = shutil.which("chromium"), shutil.which("chromedriver")
    if not all(found):
        unavailable("apt-get installed chromium and chromium-driver, but the programs are not on PATH")
    return found


class Browser:
    """Headless Chromium through chromedriver's W3C WebDriver HTTP API."""

    def __init__(self, chromium: str, chromedriver: str, profile: Path):
        port = free_port()
        self.driver = subprocess.Popen([chromedriver, f"--port={port}"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.base = f"http://127.0.0.1:{port}"
        wait_for(lambda: port_open(port), timeout=15)
        args = [*CHROMIUM_FLAGS, f"--user-data-dir={profile}"]
        capabilities = {"alwaysMatch": {"browserName": "chrome", "goog:chromeOptions": {"binary": chromium, "args": args}}}
        self.session = self.call("POST", "/session", {"capabilities": capabilities})["sessionId"]

    def call(self, method: str, path: str, body: dict | None = None):
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(self.base + path, data=data, method=method,
                                         headers={"Content-Type": "application/json"})
        try:
            with urllib.request.urlopen(request, timeout=60) as response:
                return json.loads(response.read())["value"]
        except urllib.error.HTTPError as error:
            raise AssertionError(f"webdriver {method} {path}: {error.read().decode()[:500]}") from None

    def open(self, url: str) -> None:
        self.call("POST", f"/session/{self.session}/url", {"url": url})

    def script(self, source: str):
        return self.call("POST", f"/session/{self.session}/execute/sync", {"script": source, "args": []})

    def screenshot(self) -> bytes:
        return base64.b64decode(self.call("GET", f"/session/{self.session}/screenshot"))

    def close(self) -> None:
        try:
            self.call("DELETE", f"/session/{self.session}")
        finally:
            stop(self.driver)
