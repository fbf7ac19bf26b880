"""Ego-motion estimators: one increment (forward, left, yaw, 6-DoF transform when known,
quality) per camera frame. Pure cores (numpy and OpenCV only).

    make_estimator(name, camera, params)   # "scanline", "stereo", "mono", "passthrough"
    egomotion_config(preset, config_file)  # the settings (EgomotionConfig): the service's, the run's, gridslam odometry's
    resolve_estimator(...), resolve_sharding(...)   # from them: the estimator and its parameters, the blocks

Presets (services/egomotion/presets/<name>.toml) hold an optional top-level ``estimator``
(the default estimator for that dataset) and one table of parameters per estimator,
``[scanline]``, ``[stereo]``, ``[mono]``, ``[passthrough]``: the shape of a config file's
[egomotion] table. A --config file may have that shape too (or be a whole config file), over
the preset key by key. Every parameter is declared once with its help and bounds
(services.common.settings.setting) and EgomotionConfig's tables are derived from them;
docs/egomotion.md describes them.
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


def egomotion_table(content: dict[str, Any], path: Path) -> Any:
    """The [egomotion] table of a config file's ``content``: a whole config file's [egomotion]
    table (none: no settings), or the file itself when it has the shape of that table (an
    ``estimator`` key or a table per estimator, as the presets have), so that a preset-shaped
    file of one's own works as --config."""
    if "egomotion" in content:
        return content["egomotion"]
    if any(key == "estimator" or key in ESTIMATORS or key in SHARD_SETTINGS for key in content):
        return content
    return {}


def egomotion_config(preset: str | Path | None = None, config_file: str | Path | None = None, environ=None,
                     **flags) -> BaseModel:
    """The egomotion service's settings (EgomotionConfig): the preset's (a name or a preset file,
    its estimator and tables) < the config file's [egomotion] table (or a file of that table's
    shape, egomotion_table; one sub-table per estimator, key by key over the preset's) <
    GRIDSLAM_EGOMOTION_<KEY> < ``flags`` (estimator, instances, shard_block; None: not given).
    The one resolution for the egomotion service, the runner and `gridslam odometry`. A bad
    value is a ConfigError naming its key (``[egomotion.stereo] ransac_iterations: ...``)."""
    from services.common.config import load_config

    return load_config(EgomotionConfig, "egomotion", preset=preset, config_file=Path(config_file) if config_file else None,
                       environ=environ, overrides=flags, table_of=egomotion_table)


def estimator_params(config: BaseModel, name: str) -> dict[str, Any]:
    """The parameters of estimator ``name`` an EgomotionConfig gives (the keys set, over the
    preset's: the rest are the estimator's defaults)."""
    return getattr(config, name).model_dump(exclude_unset=True)


def resolve_estimator(estimator: str | None = None, preset: str | None = None, config_file: str | Path | None = None,
                      camera_height: float | None = None, environ=None) -> tuple[str, dict[str, Any]]:
    """The estimator a run uses and its parameters (egomotion_config): scanline when none names
    one. ``camera_height`` (m) sets mono's camera_height_m."""
    config = egomotion_config(preset, config_file, environ, estimator=estimator)
    name = config.estimator or "scanline"
    params = estimator_params(config, name)
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


def _estimator_model(name: str, params: type) -> type[BaseModel]:
    """The table [egomotion.<name>]: the estimator's parameters, derived from their declaration."""
    return create_model(f"{name.capitalize()}Config", __config__=ConfigDict(frozen=True, extra="forbid"),
                        __doc__=f"The {name} estimator's parameters ({params.__name__}, docs/egomotion.md).",
                        **config_fields(params))


EgomotionConfig = create_model(
    "EgomotionConfig", __base__=_EgomotionFields, __doc__=_EgomotionFields.__doc__, **config_fields(ShardParams),
    **{name: (model, Field(default_factory=model, description=model.__doc__))
       for name, model in ((name, _estimator_model(name, params)) for name, (_, params) in ESTIMATORS.items())})


__all__ = [
    "ESTIMATORS",
    "EgomotionError",
    "Estimator",
    "EstimatorConfigError",
    "Increment",
    "EgomotionConfig",
    "egomotion_config",
    "egomotion_table",
    "estimator_params",
    "increment_from_transform",
    "make_estimator",
    "preset_names",
    "resolve_estimator",
    "resolve_sharding",
    "transform_from_increment",
]
