"""The Zenoh side of every process: the shared flag set, the runtime config it fills, and the
session built from it (STYLE.md: zenoh-python examples' common flags, built once)."""

from __future__ import annotations

import argparse
import ipaddress
import json
import logging
import threading
from pathlib import Path
from typing import Literal

import zenoh
from pydantic import BaseModel, ConfigDict, Field

from services.common.config import load_config
from services.common.errors import ConfigError
from services.common.settings import add_field_flag

log = logging.getLogger(__name__)

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
SESSION_MODES = ("client", "peer", "router")


class RuntimeConfig(BaseModel):
    """How a process joins the Zenoh network (table `[runtime]`, env `GRIDSLAM_RUNTIME_*`)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    mode: Literal[SESSION_MODES] = Field("client", description="Zenoh session mode.")
    connect: list[str] = Field(
        default_factory=lambda: [DEFAULT_ROUTER], description="Endpoints to connect to, e.g. tcp/127.0.0.1:7447 "
                                                              "(a flag per endpoint)."
    )
    listen: list[str] = Field(default_factory=list, description="Endpoints to listen on (a flag per endpoint).")
    multicast_scouting: bool = Field(False, description="Discover peers by UDP multicast (off: loopback and containers).")
    robot: str = Field("robot0", pattern=r"^[A-Za-z0-9_\-]+$", description="Robot name, the <robot> chunk of every key.")
    zenoh_config: Path | None = Field(None, description="A Zenoh JSON5 config file applied first (TLS, access control).")
    cfg: dict[str, str] = Field(default_factory=dict, description="Raw Zenoh settings KEY:VALUE, VALUE in JSON5, applied "
                                                                  "last, e.g. transport/link/tx/lease:3000.")


def is_loopback(host: str) -> bool:
    """Whether a host name or address is this machine's loopback (a server bound there is not reachable from outside)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def add_runtime_flags(parser: argparse.ArgumentParser) -> None:
    """The flag set every gridslam process shares, derived from RuntimeConfig's fields (their
    help, choices, types and defaults written there once); -c/--config names the file of them."""
    group = parser.add_argument_group("zenoh")
    add_field_flag(group, RuntimeConfig, "mode")
    add_field_flag(group, RuntimeConfig, "connect", flag=("-e", "--connect"), action="append", metavar="ENDPOINT")
    add_field_flag(group, RuntimeConfig, "listen", flag=("-l", "--listen"), action="append", metavar="ENDPOINT")
    group.add_argument("-c", "--config", type=Path, metavar="FILE", help="gridslam TOML config file ([runtime] and per-service tables)")
    add_field_flag(group, RuntimeConfig, "zenoh_config", metavar="FILE")
    add_field_flag(group, RuntimeConfig, "multicast_scouting", action=argparse.BooleanOptionalAction)
    add_field_flag(group, RuntimeConfig, "cfg", action="append", metavar="KEY:VALUE")
    add_field_flag(group, RuntimeConfig, "robot")


def parse_cfg(items: list[str] | None) -> dict[str, str] | None:
    if not items:
        return None
    pairs = {}
    for item in items:
        name, sep, value = item.partition(":")
        if not sep or not name:
            raise ConfigError(f"--cfg {item!r}: expected KEY:VALUE")
        pairs[name] = value
    return pairs


def runtime_from_args(args: argparse.Namespace, **defaults) -> RuntimeConfig:
    """RuntimeConfig from the config file, environment and flags; `defaults` replace the
    model's defaults (e.g. a router listens on the default endpoint instead of connecting)."""
    flags = {
        "mode": args.mode, "connect": args.connect, "listen": args.listen, "robot": args.robot,
        "multicast_scouting": args.multicast_scouting, "zenoh_config": args.zenoh_config, "cfg": parse_cfg(args.cfg),
    }
    return load_config(RuntimeConfig, "runtime", defaults=defaults, config_file=args.config, overrides=flags)


def zenoh_config(runtime: RuntimeConfig) -> zenoh.Config:
    """A zenoh.Config for this runtime; bad values become a one-line ConfigError."""
    try:
        if runtime.zenoh_config is not None:
            if not runtime.zenoh_config.is_file():
                raise ConfigError(f"{runtime.zenoh_config}: Zenoh config file not found")
            config = zenoh.Config.from_file(str(runtime.zenoh_config))
        else:
            config = zenoh.Config()
        config.insert_json5("mode", json.dumps(runtime.mode))
        config.insert_json5("connect/endpoints", json.dumps(runtime.connect))
        if runtime.listen:
            config.insert_json5("listen/endpoints", json.dumps(runtime.listen))
        config.insert_json5("scouting/multicast/enabled", json.dumps(runtime.multicast_scouting))
        if runtime.mode == "client":
            # One try per endpoint when opening: the caller stays responsive to signals (a native
            # call blocked inside zenoh.open never runs Python's handlers), open_session's loop
            # retries, and a first router that is down does not hide the next one. Once open,
            # a lost router is retried at a short period so that a restarted router is
            # rejoined within a second (issue 7); the default backs off to several seconds.
            config.insert_json5("connect/timeout_ms", "0")
            config.insert_json5("connect/retry", '{"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 1.5}')
        for name, value in runtime.cfg.items():
            config.insert_json5(name, value)
    except ConfigError:
        raise
    except Exception as error:  # zenoh raises ZError or ValueError with its own text
        # (Zenoh's parser errors span several lines; the message must stay one.)
        raise ConfigError(f"invalid Zenoh configuration: {' '.join(str(error).split())}") from None
    return config


def open_session(runtime: RuntimeConfig, stop: threading.Event | None = None) -> zenoh.Session:
    """Open the process's one Zenoh session (DESIGN.md, "Runtime").

    Without `stop`, one attempt: a client that cannot reach its router is a one-line
    ConfigError. With `stop`, a service keeps trying until the router answers or `stop` is set
    (services may start before the router); it then raises ServiceStopped."""
    config = zenoh_config(runtime)
    attempt = 0
    while True:
        attempt += 1
        try:
            session = zenoh.open(config)
            break
        except Exception as error:
            if stop is None:
                raise ConfigError(f"cannot open a Zenoh session ({runtime.mode}, connect {runtime.connect}, "
                                  f"listen {runtime.listen}): {' '.join(str(error).split())}") from None
            if attempt == 1:
                log.warning("waiting for a Zenoh router at %s (%s)", ", ".join(runtime.connect), error)
            if stop.wait(0.2):
                raise ServiceStopped("stopped before a Zenoh session could be opened") from None
    log.info("zenoh session %s open (%s)", session.info.zid(), runtime.mode)
    return session


class ServiceStopped(Exception):
    """A stop was requested while the session was still being opened."""
