"""Ego-motion estimators: one increment (forward, left, yaw, 6-DoF transform when known,
quality) per camera frame. Pure cores (numpy and OpenCV only).

    make_estimator(name, camera, params)   # "scanline", "stereo", "mono", "passthrough"
    egomotion_config(preset, config_file)  # the service's settings (EgomotionConfig), as every service reads its own
    resolve_estimator(...), resolve_sharding(...)   # from them: the estimator and its parameters, the blocks
    load_estimator_config(preset, config_file) -> (default estimator name, {name: params})   # gridslam odometry

Presets (services/egomotion/presets/<name>.toml) hold an optional top-level ``estimator``
(the default estimator for that dataset) and one table of parameters per estimator,
``[scanline]``, ``[stereo]``, ``[mono]``, ``[passthrough]``: the shape of a config file's
[egomotion] table. `gridslam odometry --config` takes a file of that shape (or a whole config
file), over the preset key by key. docs/egomotion.md describes every parameter.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, create_model

from services.common.geometry import increment_from_transform, transform_from_increment
from services.common.settings import config_fields
from services.common.stages import ESTIMATORS as ESTIMATOR_NAMES
from services.egomotion.base import (
    EgomotionError,
    Estimator,
    EstimatorConfigError,
    Increment,
    params_from_dict,
)
from services.egomotion.mono import MonoEstimator, MonoParams
from services.egomotion.passthrough import PassthroughEstimator, PassthroughParams
from services.egomotion.scanline import ScanlineEstimator, ScanlineParams
from services.egomotion.shards import ShardParams, block_size
from services.egomotion.stereo import StereoEstimator, StereoParams

ESTIMATORS: dict[str, tuple[type, type]] = {
    "scanline": (ScanlineEstimator, ScanlineParams),
    "stereo": (StereoEstimator, StereoParams),
    "mono": (MonoEstimator, MonoParams),
    "passthrough": (PassthroughEstimator, PassthroughParams),
}
PRESET_DIR = Path(__file__).resolve().parent / "presets"
SHARD_SETTINGS = tuple(f.name for f in dataclasses.fields(ShardParams))   # [egomotion] keys beside the estimators'


def make_estimator(name: str, camera: Any = None, params: dict[str, Any] | None = None) -> Estimator:
    """The estimator called ``name`` with ``params`` (a dict of its parameter fields; missing
    ones take their defaults). ``camera`` (source Camera: fx, fy, cx, cy, baseline) is needed
    by stereo (with a baseline) and mono; frames that carry their own camera override it.
    Raises EstimatorConfigError for an unknown name or parameter or a missing calibration."""
    if name not in ESTIMATORS:
        raise EstimatorConfigError(f"unknown estimator {name!r} (available: {', '.join(ESTIMATORS)})")
    estimator_class, params_class = ESTIMATORS[name]
    parameters = params_from_dict(params_class, params, where=f"{name} parameters")
    if name == "stereo" and (camera is None or getattr(camera, "baseline", 0.0) <= 0):
        raise EstimatorConfigError(
            "the stereo estimator needs a stereo calibration (a camera with a baseline > 0): "
            "use a stereo source with its calibration, --preset or --calibration"
        )
    if name == "mono" and camera is None:
        raise EstimatorConfigError(
            "the mono estimator needs camera intrinsics (fx, fy, cx, cy): use --preset or --calibration"
        )
    return estimator_class(parameters, camera)


def preset_names() -> list[str]:
    return sorted(path.stem for path in PRESET_DIR.glob("*.toml"))


def read_config_file(path: str | Path) -> dict[str, Any]:
    """A preset or config TOML file, shape-checked: optional ``estimator`` string and one
    table per estimator name; or a whole gridslam config file, whose [egomotion] table has that
    shape (and the instances' keys, which an offline run has no use for)."""
    from services.common.config import read_toml

    table = read_toml(path, error=EstimatorConfigError)
    if isinstance(table.get("egomotion"), dict):
        table = {key: value for key, value in table["egomotion"].items() if key not in SHARD_SETTINGS}
        return check_config_table(table, f"{path}: [egomotion]")
    return check_config_table(table, str(path))


def check_config_table(table: dict[str, Any], where: str) -> dict[str, Any]:
    """``table`` if it has the shape of an estimator preset (optional ``estimator`` string and
    one table per estimator name, each of known parameters), else EstimatorConfigError naming ``where``."""
    for key, value in table.items():
        if key == "estimator":
            if value not in ESTIMATORS:
                raise EstimatorConfigError(f"{where}: estimator {value!r} is not one of {', '.join(ESTIMATORS)}")
        elif key in ESTIMATORS:
            if not isinstance(value, dict):
                raise EstimatorConfigError(f"{where}: [{key}] must be a table of parameters")
            params_from_dict(ESTIMATORS[key][1], value, where=f"{where}: [{key}]")
        else:
            raise EstimatorConfigError(
                f"{where}: unknown key {key!r} (expected 'estimator' or a table [{'], ['.join(ESTIMATORS)}])"
            )
    return table


def load_estimator_config(
    preset: str | None = None, config_file: str | Path | None = None
) -> tuple[str | None, dict[str, dict[str, Any]]]:
    """The default estimator name (or None) and the parameters of every estimator, from a
    preset (a name, or a preset file: its [egomotion] table over its base's,
    services/common/config.py) and/or a config file (the file overrides the preset key by key)."""
    from services.common.config import is_preset_file, preset_values

    default: str | None = None
    params: dict[str, dict[str, Any]] = {name: {} for name in ESTIMATORS}
    tables: list[dict[str, Any]] = []
    if preset is not None:
        if is_preset_file(preset):
            tables.append(check_config_table(preset_values("egomotion", preset), f"{preset}: [egomotion]"))
        elif preset in preset_names():
            tables.append(read_config_file(PRESET_DIR / f"{preset}.toml"))
        else:
            raise EstimatorConfigError(f"unknown estimator preset {preset!r} (available: {', '.join(preset_names())})")
    if config_file is not None:
        tables.append(read_config_file(config_file))
    for table in tables:
        default = table.get("estimator", default)
        for name in ESTIMATORS:
            params[name].update(table.get(name, {}))
    return default, params


def egomotion_config(preset: str | Path | None = None, config_file: str | Path | None = None, environ=None,
                     **flags) -> BaseModel:
    """The egomotion service's settings (EgomotionConfig): the preset's (a name or a preset file,
    its estimator and tables) < the config file's [egomotion] table (one sub-table per estimator,
    key by key over the preset's) < GRIDSLAM_EGOMOTION_<KEY> < ``flags`` (estimator, instances,
    shard_block; None: not given). The one resolution for the egomotion service and the runner."""
    from services.common.config import load_config

    return load_config(EgomotionConfig, "egomotion", preset=preset, config_file=Path(config_file) if config_file else None,
                       environ=environ, overrides=flags)


def resolve_estimator(estimator: str | None = None, preset: str | None = None, config_file: str | Path | None = None,
                      camera_height: float | None = None, environ=None) -> tuple[str, dict[str, Any]]:
    """The estimator a run uses and its parameters (egomotion_config): scanline when none names
    one. ``camera_height`` (m) sets mono's camera_height_m."""
    config = egomotion_config(preset, config_file, environ, estimator=estimator)
    name = config.estimator or "scanline"
    params = dict(getattr(config, name))
    if camera_height is not None and name == "mono":
        params["camera_height_m"] = camera_height
    params_from_dict(ESTIMATORS[name][1], params, where=f"{name} parameters")   # fail at start, not at frame 1
    return name, params


def resolve_sharding(estimator: str, instances: int | None = None, shard_block: int | None = None,
                     config_file: str | Path | None = None, environ=None) -> tuple[ShardParams, int | None]:
    """How this robot's egomotion instances share its frames (shards.ShardParams) and the frames
    per block they run `estimator` in (None: one instance, frame after frame; shards.block_size),
    from egomotion_config (``instances`` and ``shard_block``: the flags; None: not given)."""
    from services.common.settings import params_of

    config = egomotion_config(None, config_file, environ, instances=instances, shard_block=shard_block)
    sharding = params_of(ShardParams, config)
    return sharding, block_size(ESTIMATORS[estimator][0], sharding)


class _EgomotionFields(BaseModel):
    """Configuration of the egomotion service (table `[egomotion]`, env `GRIDSLAM_EGOMOTION_*`,
    presets): the estimator, one table of parameters per estimator (docs/egomotion.md) and how
    the instances share the frames (ShardParams)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    estimator: Literal[ESTIMATOR_NAMES] | None = Field(
        None, description="The ego-motion estimator (default: the preset's, else scanline).")


EgomotionConfig = create_model(
    "EgomotionConfig", __base__=_EgomotionFields, __doc__=_EgomotionFields.__doc__, **config_fields(ShardParams),
    **{name: (dict[str, Any], Field(default_factory=dict, description=f"The {name} estimator's parameters "
                                                                       f"({params.__name__})."))
       for name, (_, params) in ESTIMATORS.items()})


__all__ = [
    "ESTIMATORS",
    "EgomotionError",
    "Estimator",
    "EstimatorConfigError",
    "Increment",
    "EgomotionConfig",
    "check_config_table",
    "egomotion_config",
    "increment_from_transform",
    "load_estimator_config",
    "make_estimator",
    "preset_names",
    "read_config_file",
    "resolve_estimator",
    "resolve_sharding",
    "transform_from_increment",
]
