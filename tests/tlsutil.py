"""Helpers for the TLS and access-control tests: certificates made by the documented command
(deploy/make-certs.sh) into a test folder, and the deploy/ Zenoh configs with their
certificate paths pointed at that folder (the rest of each file is used as shipped)."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from services.common.runtime import RuntimeConfig
from tests.netutil import REPO

DEPLOY = REPO / "deploy"
MAKE_CERTS = DEPLOY / "make-certs.sh"
ROUTER_MTLS_ACL = DEPLOY / "acl" / "router.json5"
CLIENT_TLS = DEPLOY / "tls" / "client-tls.json5"
CLIENT_MTLS = DEPLOY / "tls" / "client-mtls.json5"
ROUTER_TLS = DEPLOY / "tls" / "router-tls.json5"
ROUTER_MTLS = DEPLOY / "tls" / "router-mtls.json5"


def make_certs(out: Path, *router_names: str) -> Path:
    """Run `deploy/make-certs.sh OUT ROUTER_NAME...`; skips where bash or openssl is missing."""
    for tool in ("bash", "openssl"):
        if shutil.which(tool) is None:
            pytest.skip(f"{tool} is not installed; deploy/make-certs.sh needs it")
    result = subprocess.run(["bash", str(MAKE_CERTS), str(out), *router_names], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    return out


def tls_paths(certs: Path, role: str) -> dict[str, str]:
    """Raw Zenoh settings (RuntimeConfig.cfg / --cfg) pointing every certificate path of the
    deploy/ configs at `role`'s files in `certs`; keys a config does not use are harmless."""
    tls = "transport/link/tls"
    pem, key = json.dumps(str(certs / f"{role}.pem")), json.dumps(str(certs / f"{role}.key"))
    return {
        f"{tls}/root_ca_certificate": json.dumps(str(certs / "ca.pem")),
        f"{tls}/listen_certificate": pem, f"{tls}/listen_private_key": key,
        f"{tls}/connect_certificate": pem, f"{tls}/connect_private_key": key,
    }


def cfg_flags(certs: Path, role: str) -> list[str]:
    """The same settings as command-line flags: --cfg KEY:VALUE ..."""
    return [arg for name, value in tls_paths(certs, role).items() for arg in ("--cfg", f"{name}:{value}")]


def tls_endpoint(port: int, host: str = "localhost") -> str:
    return f"tls/{host}:{port}"


def router_runtime(port: int, zenoh_config: Path, certs: Path) -> RuntimeConfig:
    return RuntimeConfig(mode="router", listen=[tls_endpoint(port, "127.0.0.1")], connect=[], zenoh_config=zenoh_config,
                         cfg=tls_paths(certs, "router"))


def client_runtime(port: int, zenoh_config: Path, certs: Path, role: str, host: str = "localhost") -> RuntimeConfig:
    return RuntimeConfig(connect=[tls_endpoint(port, host)], zenoh_config=zenoh_config, cfg=tls_paths(certs, role))
