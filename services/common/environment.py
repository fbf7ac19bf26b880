"""Settings of the whole process that only the environment gives (no config table, no flag):
which FFT library the grid network uses and where measured lattice flow tables are cached.
Declared once here (name, default, help, allowed values); `process_params` is their one reader,
and the variable of each is GRIDSLAM_<NAME>. Also the one BLAS kernel every gridslam process
computes with (`pin_blas_kernel`), so that a run gives the same figures on every machine."""

from __future__ import annotations

import dataclasses
import os
import platform
from collections.abc import Mapping, MutableMapping
from dataclasses import dataclass
from pathlib import Path

from services.common.errors import ConfigError
from services.common.settings import setting

# OpenBLAS picks its kernels by the CPU it finds, and kernels of different vector widths round
# differently; the stereo estimator's RANSAC turns those last bits into other inliers, so the
# demo's odometry error was 0.0496 m with the Haswell/Zen kernels, 0.0453 m with SkylakeX's and
# 0.0465 m with Sapphire Rapids' (gridslam odometry --source synthetic:0 --preset synthetic
# --laps 2, OPENBLAS_CORETYPE set by hand). Haswell's kernels (AVX2 and FMA) run on every x86-64
# CPU of the last ten years; the matrices here are small, so wider kernels gain nothing.
BLAS_KERNEL = ("OPENBLAS_CORETYPE", "Haswell")


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


def pin_blas_kernel(environ: MutableMapping[str, str] | None = None, cpu_flags: set[str] | None = None) -> bool:
    """Set OPENBLAS_CORETYPE to BLAS_KERNEL's in ``environ`` (os.environ) unless it is set, on an
    x86-64 CPU that has the kernel's instructions (``cpu_flags``: /proc/cpuinfo's), so that this
    process and the services it starts compute the same figures on every such machine. Called
    before numpy is first imported (OpenBLAS reads the variable once, as it loads). Whether it
    set the variable."""
    environ = os.environ if environ is None else environ
    name, kernel = BLAS_KERNEL
    if name in environ or platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    flags = _cpu_flags() if cpu_flags is None else cpu_flags
    if not {"avx2", "fma"} <= flags:
        return False
    environ[name] = kernel
    return True


def _cpu_flags() -> set[str]:
    """The instruction set flags of the first CPU in /proc/cpuinfo (none where it cannot be read)."""
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            line = next((line for line in cpuinfo if line.startswith("flags")), "")
    except OSError:
        return set()
    return set(line.partition(":")[2].split())
