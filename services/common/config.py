"""Configuration: one pydantic model per concern, filled from (lowest to highest precedence)
defaults, a per-dataset preset, the `--config` TOML file, environment variables (for
containers) and command-line flags (STYLE.md, habit 8).

A config file is TOML with one table per concern: `[runtime]` for the Zenoh session and
`[<service>]` (e.g. `[gridcells]`) for a service. Presets live beside each service as
`services/<service>/presets/<name>.toml`, a flat table of that service's fields. Environment
variables are `GRIDSLAM_<SECTION>_<FIELD>` in upper case, e.g. `GRIDSLAM_RUNTIME_CONNECT`
or `GRIDSLAM_GRIDCELLS_DECODER`; list fields take comma-separated values.

A preset may also be a file of one's own (a path ending in .toml): `base = "NAME"` names the
preset it builds on, and one table per service (`[source]`, `[loopclosure]`, ...) holds the
keys that replace the base's, key by key (one level deep: `[egomotion.stereo]` replaces single
parameters). A service the file has no table for stays on the base's preset (or its defaults,
without a base). Top-level keys other than `base` are source keys (the older flat shape).
`preset_values` reads both kinds, so every service that loads a preset takes files too.
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar, get_origin

from pydantic import BaseModel, ValidationError

from services.common.errors import ConfigError

SERVICES_DIR = Path(__file__).resolve().parents[1]
ENV_PREFIX = "GRIDSLAM_"

ModelT = TypeVar("ModelT", bound=BaseModel)

# The services (name → adapter module) and so the tables of a config file: [runtime], [run] and
# one per service. `gridslam service NAME` starts them by these modules (imported only for the
# service being started); a config file's table of another name is refused.
SERVICE_MODULES: dict[str, str] = {
    "source": "services.source.service",
    "egomotion": "services.egomotion.service",
    "gridcells": "services.gridcells.service",
    "loopclosure": "services.loopclosure.service",
    "expmap": "services.expmap.service",
    "fleetmap": "services.fleetmap.service",
    "viewer": "services.viewer.service",
    "foxglove": "services.ros.foxglove",
    "ros2": "services.ros.node",
}
SECTIONS = ("runtime", "run", *SERVICE_MODULES)


def read_toml(path: str | Path, what: str = "config file", error: type[Exception] = ConfigError) -> dict[str, Any]:
    """Parse a TOML file (a config, preset or calibration file: ``what``, in messages): the one
    TOML reader. A missing or malformed file is a one-line ``error`` (ConfigError, or the
    caller's own kind of it) naming the file."""
    try:
        with open(path, "rb") as handle:
            return tomllib.load(handle)
    except FileNotFoundError:
        raise error(f"{path}: {what} not found") from None
    except OSError as problem:
        raise error(f"{path}: cannot read {what} ({problem.strerror})") from None
    except tomllib.TOMLDecodeError as problem:
        raise error(f"{path}: not valid TOML ({problem})") from None


def presets(service: str) -> list[str]:
    """Names of the presets a service ships."""
    return sorted(p.stem for p in (SERVICES_DIR / service / "presets").glob("*.toml"))


def preset_services() -> list[str]:
    """The services that have presets (the tables a preset file may hold)."""
    return sorted(p.parent.name for p in SERVICES_DIR.glob("*/presets"))


def is_preset_file(preset: str | Path) -> bool:
    """Whether ``preset`` names a file (a path or a name ending in .toml) rather than a shipped preset."""
    text = str(preset)
    return text.endswith(".toml") or "/" in text or "\\" in text


def has_named_preset(service: str, name: str) -> bool:
    return (SERVICES_DIR / service / "presets" / f"{name}.toml").is_file()


def read_preset_file(path: str | Path) -> tuple[str | None, dict[str, dict[str, Any]]]:
    """A preset file's base (or None) and its tables by service, checked: a missing file, an
    unknown base or table, or a table that is not one is a one-line ConfigError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: preset file not found")
    content = read_toml(path)
    base = content.pop("base", None)
    services = preset_services()
    if base is not None:
        if not isinstance(base, str) or not any(has_named_preset(service, base) for service in services):
            names = sorted({name for service in services for name in presets(service)})
            raise ConfigError(f"{path}: base {base!r} is not a preset (available: {', '.join(names)})")
    tables = {key: value for key, value in content.items() if isinstance(value, dict)}
    flat = {key: value for key, value in content.items() if not isinstance(value, dict)}
    for key in tables:
        if key not in services:
            raise ConfigError(f"{path}: unknown table [{key}] (a preset file holds base and the tables "
                              f"{', '.join(f'[{s}]' for s in services)})")
    if flat:
        if "source" in tables:
            raise ConfigError(f"{path}: key {next(iter(flat))!r} outside a table while the file has a [source] table "
                              f"(put the source's keys in [source])")
        tables["source"] = flat
    return base, tables


def preset_values(service: str, preset: str | Path) -> dict[str, Any]:
    """The settings a preset gives ``service``: a shipped preset's file, or for a preset file
    its base's preset for the service (if any) with the file's table for it on top."""
    if is_preset_file(preset):
        base, tables = read_preset_file(preset)
        values = preset_values(service, base) if base is not None and has_named_preset(service, base) else {}
        return merge_tables(values, tables.get(service, {}))
    if not has_named_preset(service, str(preset)):
        available = ", ".join(presets(service)) or "none"
        raise ConfigError(f"unknown preset {preset!r} for {service} (available: {available})")
    return read_toml(SERVICES_DIR / service / "presets" / f"{preset}.toml")


def preset_applies(service: str, preset: str | Path) -> bool:
    """Whether ``preset`` gives ``service`` any settings (a preset file: a table for it, or a
    base that has a preset for it)."""
    if not is_preset_file(preset):
        return has_named_preset(service, str(preset))
    base, tables = read_preset_file(preset)
    return service in tables or (base is not None and has_named_preset(service, base))


def describe_preset(preset: str | Path, services: list[str]) -> str:
    """One line saying where each service's preset settings come from, for a preset file."""
    base, tables = read_preset_file(preset)
    from_file = [s for s in services if s in tables]
    on_base = [s for s in services if s not in tables and base is not None and has_named_preset(s, base)]
    default = [s for s in services if s not in from_file and s not in on_base]

    def say(names: list[str], one: str, many: str) -> str:
        return f"{', '.join(names)} {one if len(names) == 1 else many}"

    parts = []
    if from_file:
        parts.append(say(from_file, "takes", "take") + " keys from it" + (f" (over preset {base!r})" if base else ""))
    if on_base:
        parts.append(say(on_base, "stays", "stay") + f" on preset {base!r}")
    if default:
        parts.append(say(default, "runs", "run") + " on defaults (" + ("no base" if base is None else f"{base!r} has no preset for it") + ")")
    return f"preset file {preset}: " + "; ".join(parts)


def merge_tables(values: dict[str, Any], table: Mapping[str, Any]) -> dict[str, Any]:
    """``table``'s keys over ``values``, one level deep: a sub-table (``[egomotion.stereo]``)
    replaces single keys of the one below it, as a preset file's tables do."""
    for key, value in table.items():
        if isinstance(value, dict) and isinstance(values.get(key), dict):
            values[key] = {**values[key], **value}
        else:
            values[key] = value
    return values


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
    preset: str | Path | None = None,
    config_file: Path | None = None,
    overrides: Mapping[str, Any] | None = None,
    environ: Mapping[str, str] | None = None,
    flags: Mapping[str, str] | None = None,
    table_of: Callable[[dict[str, Any], Path], Any] | None = None,
) -> ModelT:
    """Build `model` for `section` from defaults < preset < config file < environment < overrides
    (flags). Overrides whose value is None are ignored, so argparse defaults of None mean "not given".
    ``table_of(content, path)``: the section's table of a config file's content (default: its
    ``[section]`` table), for a section whose own table may also be a file of its own.
    A bad value is a ConfigError naming where it came from: the flag (`flags` maps a field to
    its flag where that is not --FIELD-NAME), the environment variable, or the file and key."""
    values: dict[str, Any] = dict(defaults or {})
    sources: list[str] = []
    given: dict[str, str] = {}   # field → the flag or environment variable that gave it
    if preset:
        merge_tables(values, preset_values(section, preset))
        sources.append(f"preset file {preset}" if is_preset_file(preset) else f"preset {preset!r}")
    if config_file is not None:
        content = read_toml(config_file)
        table = table_of(content, config_file) if table_of is not None else content.get(section, {})
        if table is not content:   # a whole config file (not one of a table's own shape): its tables are known
            unknown = [key for key, value in content.items() if isinstance(value, dict) and key not in (*SECTIONS, section)]
            if unknown:
                raise ConfigError(f"{config_file}: unknown table [{unknown[0]}] (a config file holds "
                                  f"{', '.join(f'[{name}]' for name in SECTIONS)})")
        if not isinstance(table, dict):
            raise ConfigError(f"{config_file}: [{section}] must be a table")
        merge_tables(values, table)
        sources.append(str(config_file))
    from_environment = env_values(section, model, environ)
    values.update(from_environment)
    given.update({name: f"{ENV_PREFIX}{section}_{name}".upper() for name in from_environment})
    from_flags = {k: v for k, v in (overrides or {}).items() if v is not None}
    values.update(from_flags)
    given.update({name: (flags or {}).get(name, "--" + name.replace("_", "-")) for name in from_flags})
    try:
        return model.model_validate(values)
    except ValidationError as error:
        first = error.errors()[0]
        loc = [str(part) for part in first["loc"]]
        name = loc[0] if loc else None
        # a key of a sub-table ([egomotion.stereo] ransac_iterations) is named as a TOML file names it
        nested = len(loc) > 1 and isinstance(first["loc"][1], str)
        table, where = (f"{section}.{loc[0]}", ".".join(loc[1:])) if nested else (section, ".".join(loc) or section)
        shown = "input" in first and not isinstance(first["input"], dict) and first.get("type") != "extra_forbidden"
        got = f", got {first['input']!r}" if shown else ""   # an unknown key's value says nothing
        if name in given:
            raise ConfigError(f"{given[name]}: {first['msg']}{got} ([{table}] {where})") from None
        origin = f" (from {', '.join(sources)})" if sources else ""
        raise ConfigError(f"[{table}] {where}: {first['msg']}{got}{origin}") from None
