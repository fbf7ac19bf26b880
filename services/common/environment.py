"""Settings of the whole process that only the environment gives (no config table, no flag):
which FFT library the grid network uses and where measured lattice flow tables are cached.
Declared once here (name, default, help, allowed values); `process_params` is their one reader,
and the variable of each is GRIDSLAM_<NAME>."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from services.common.errors import ConfigError
from services.common.settings import setting


@dataclass(frozen=True)
class ProcessParams:
    fft: str = setting("auto", choices=("auto", "fftw", "scipy"),
                       help="FFT library of the grid network: pyFFTW when it is installed, else scipy.fft (auto); "
                            "fftw requires pyFFTW; scipy forces scipy.fft")
    cache: str = setting("", help="folder of the measured lattice flow tables (empty: $XDG_CACHE_HOME/gridslam, "
                                  "else ~/.cache/gridslam)")


def variable(name: str) -> str:
    """The environment variable of the process setting ``name``."""
    return f"GRIDSLAM_{name.upper()}"


VARIABLES = tuple(variable(f.name) for f in dataclasses.fields(ProcessParams))


def process_setting(name: str, environ: Mapping[str, str] | None = None) -> str:
    """The process setting ``name`` from its variable (unset or empty: the default); a value
    outside its choices is a ConfigError naming the variable."""
    environ = os.environ if environ is None else environ
    field = next(f for f in dataclasses.fields(ProcessParams) if f.name == name)
    raw = environ.get(variable(name), "").strip()
    if not raw:
        return field.default
    choices = field.metadata.get("choices")
    if choices:
        raw = raw.lower()
        if raw not in choices:
            raise ConfigError(f"{variable(name)}={raw!r}: choose one of {', '.join(choices)}")
    return raw


def process_params(environ: Mapping[str, str] | None = None) -> ProcessParams:
    """Every process setting (process_setting)."""
    return ProcessParams(**{f.name: process_setting(f.name, environ) for f in dataclasses.fields(ProcessParams)})


def cache_folder(environ: Mapping[str, str] | None = None) -> Path:
    """Where measured tables are cached: `cache` (GRIDSLAM_CACHE), else $XDG_CACHE_HOME/gridslam,
    else ~/.cache/gridslam."""
    environ = os.environ if environ is None else environ
    folder = process_setting("cache", environ)
    if folder:
        return Path(folder)
    base = Path(environ["XDG_CACHE_HOME"]) if environ.get("XDG_CACHE_HOME") else Path.home() / ".cache"
    return base / "gridslam"
