"""Configuration: one pydantic model per concern, filled from (lowest to highest precedence)
defaults, a per-dataset preset, the `--config` TOML file, environment variables (for
containers) and command-line flags (STYLE.md, habit 8).

A config file is TOML with one table per concern: `[runtime]` for the Zenoh session and
`[<service>]` (e.g. `[gridcells]`) for a service. Presets live beside each service as
`services/<service>/presets/<name>.toml`, a flat table of that service's fields. Environment
variables are `GRIDSLAM_<SECTION>_<FIELD>` in upper case, e.g. `GRIDSLAM_RUNTIME_CONNECT`
or `GRIDSLAM_GRIDCELLS_DECODER`; list fields take comma-separated values.
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar, get_origin

from pydantic import BaseModel, ValidationError

from services.common.errors import ConfigError

SERVICES_DIR = Path(__file__).resolve().parents[1]
ENV_PREFIX = "GRIDSLAM_"

ModelT = TypeVar("ModelT", bound=BaseModel)


def read_toml(path: Path) -> dict[str, Any]:
    """Parse a TOML file; a missing or malformed file is a one-line ConfigError naming it."""
    try:
        with open(path, "rb") as handle:
            return tomllib.load(handle)
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except OSError as error:
        raise ConfigError(f"{path}: cannot read config file ({error.strerror})") from None
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{path}: not valid TOML ({error})") from None


def presets(service: str) -> list[str]:
    """Names of the presets a service ships."""
    return sorted(p.stem for p in (SERVICES_DIR / service / "presets").glob("*.toml"))


def preset_values(service: str, preset: str) -> dict[str, Any]:
    path = SERVICES_DIR / service / "presets" / f"{preset}.toml"
    if not path.is_file():
        available = ", ".join(presets(service)) or "none"
        raise ConfigError(f"unknown preset {preset!r} for {service} (available: {available})")
    return read_toml(path)


def env_values(section: str, model: type[BaseModel], environ: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Fields of `model` set through `GRIDSLAM_<SECTION>_<FIELD>` environment variables."""
    environ = os.environ if environ is None else environ
    values: dict[str, Any] = {}
    for name, field in model.model_fields.items():
        raw = environ.get(f"{ENV_PREFIX}{section}_{name}".upper())
        if raw is None:
            continue
        is_list = get_origin(field.annotation) in (list, tuple) or field.annotation in (list, tuple)
        values[name] = [item.strip() for item in raw.split(",") if item.strip()] if is_list else raw
    return values


def load_config(
    model: type[ModelT],
    section: str,
    *,
    defaults: Mapping[str, Any] | None = None,
    preset: str | None = None,
    config_file: Path | None = None,
    overrides: Mapping[str, Any] | None = None,
    environ: Mapping[str, str] | None = None,
) -> ModelT:
    """Build `model` for `section` from defaults < preset < config file < environment < overrides
    (flags). Overrides whose value is None are ignored, so argparse defaults of None mean "not given"."""
    values: dict[str, Any] = dict(defaults or {})
    sources: list[str] = []
    if preset:
        values.update(preset_values(section, preset))
        sources.append(f"preset {preset!r}")
    if config_file is not None:
        table = read_toml(config_file).get(section, {})
        if not isinstance(table, dict):
            raise ConfigError(f"{config_file}: [{section}] must be a table")
        values.update(table)
        sources.append(str(config_file))
    values.update(env_values(section, model, environ))
    values.update({k: v for k, v in (overrides or {}).items() if v is not None})
    try:
        return model.model_validate(values)
    except ValidationError as error:
        first = error.errors()[0]
        where = ".".join(str(part) for part in first["loc"]) or section
        origin = f" (from {', '.join(sources)})" if sources else ""
        raise ConfigError(f"[{section}] {where}: {first['msg']}{origin}") from None
