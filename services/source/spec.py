"""Open any source from a one-word spec, ``KIND:TARGET``:

    kitti:PATH      KITTI odometry sequence (official layout) or flat clip (datasets.KittiSequence)
    stereo:PATH     stereo pair folder: left/ + right/, or NuBot {k}L.ppm/{k}R.ppm (datasets.StereoFolder)
    images:PATH     folder of monocular images, natural name order (datasets.ImageFolder)
    video:FILE      video file OpenCV decodes (datasets.VideoFile)
    camera:N        live camera N (or a device path / stream URL), newest frame only (camera.LiveCamera)
    synthetic:SEED  procedural world rendered on the fly (synthetic.SyntheticWorld)
    rosbag:PATH     ROS 1 .bag, or ROS 2 bag folder / .db3 / .mcap file (rosbag.RosbagSource; extra `ros`)
    ros2:TOPIC      live ROS 2 image topic over Zenoh, newest frame only (ros2.Ros2Source; extra `ros`)

A preset (``services/source/presets/<name>.toml``) is a flat TOML table of calibration keys
(calibration.py) and source settings (``fps``, ``grey``, the topics of a ROS bag, and for the
synthetic world the fields of ``synthetic.WorldConfig``); a preset file of one's own gives its
``[source]`` table over its base's (services/common/config.py). An explicit calibration (a file
of our format or a Camera) wins over the preset's, and either wins over the dataset's own;
``world`` settings win over the preset's. A preset describes a dataset however it is stored:
its bag topics are ignored by the other kinds (St Lucia is a video and a bag).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from services.common.errors import ConfigError
from services.common.settings import add_flag, setting
from services.source.calibration import CALIBRATION_KEYS, DEFAULT_FOV_DEG, assumed_camera, camera_from_mapping, read_calibration
from services.common.frames import Camera, FrameSource, SourceError

PRESET_DIR = Path(__file__).resolve().parent / "presets"
KINDS = ("kitti", "stereo", "images", "video", "camera", "synthetic", "rosbag", "ros2")
MONOCULAR_KINDS = ("images", "video", "camera")   # without a calibration, a pinhole camera is assumed (``fov``)
@dataclasses.dataclass(frozen=True)
class BagParams:
    """The settings of a ROS bag (rosbag.RosbagSource) and of a live ros2: source: preset keys,
    `[source]` keys and flags of the same names, shared by `gridslam run`, `odometry` and the
    source service, declared once here."""

    image_topic: str | None = setting(None, help="ROS bag: image topic, sensor_msgs/Image or CompressedImage "
                                                 "(default: the bag's only one)")
    right_image_topic: str | None = setting(None, help="ROS bag or ros2: right image topic of a stereo pair, matched "
                                                       "by stamp")
    camera_info_topic: str | None = setting(None, help="ROS bag or ros2: sensor_msgs/CameraInfo topic (a bag's "
                                                       "default: the image topic's camera_info)")
    odom_topic: str | None = setting(None, help="ROS bag or ros2: nav_msgs/Odometry topic (passthrough estimator; "
                                                "ground truth where the run has none)")
    stereo_tolerance: float | None = setting(None, gt=0, help="ROS bag or ros2: seconds between the stamps of a "
                                                              "stereo pair, at most (default 0.005)")


BAG_KEYS = tuple(f.name for f in dataclasses.fields(BagParams))
# Source settings a preset may hold besides the calibration, with their types.
SETTINGS: dict[str, type] = {"fps": float, "grey": bool, "fov": float,
                             **{key: float if key == "stereo_tolerance" else str for key in BAG_KEYS}}


def add_bag_arguments(parser) -> None:
    """The ROS bag flags (--image-topic, ...) on an argparse parser; the defaults are None."""
    for key in BAG_KEYS:
        add_flag(parser, BagParams, key, metavar="S" if key == "stereo_tolerance" else "TOPIC")


def bag_settings(values) -> dict:
    """The ROS bag settings of an argparse namespace or a config model (None where not given)."""
    return {key: getattr(values, key, None) for key in BAG_KEYS}


def preset_names() -> list[str]:
    """Names of the presets shipped with the project."""
    return sorted(path.stem for path in PRESET_DIR.glob("*.toml"))


def world_keys() -> dict[str, type]:
    """The synthetic world's settings (``synthetic.WorldConfig``'s fields but the seed, which
    comes from the spec) and their types: keys of a preset, of ``[source]`` and of ``--world``."""
    from services.source.synthetic import WorldConfig

    types = {"int": int, "float": float, "bool": bool, "str": str}
    return {field.name: types.get(str(field.type), float) for field in dataclasses.fields(WorldConfig) if field.name != "seed"}


def check_setting(key: str, value: Any, expected: type, where: str) -> Any:
    """``value`` as ``expected`` (an int is a float too), or a one-line ConfigError naming ``where`` and the key."""
    if expected is str:
        ok = isinstance(value, str)
    elif expected is bool:
        ok = isinstance(value, bool)
    else:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and (expected is float or isinstance(value, int))
    if not ok:
        raise ConfigError(f"{where}: key {key!r} must be {expected.__name__}, got {value!r}")
    return expected(value)


def add_world_arguments(parser) -> None:
    """``--laps N`` and ``--world KEY=VALUE``: the synthetic world's settings as flags (the
    source service, `gridslam run` and `demo`); ``parse_world_flags`` reads them."""
    parser.add_argument("--laps", type=int, help="synthetic world: laps of its route (over the preset's and the config file's)")
    parser.add_argument("--world", action="append", metavar="KEY=VALUE",
                        help="synthetic world setting over the preset's and the config file's [source] keys, repeatable "
                             "(layout, speed, laps, lamps_off, ...: docs/sources.md)")


def parse_world_flags(pairs: list[str] | None, laps: int | None = None) -> dict[str, Any]:
    """``--world KEY=VALUE`` flags (and ``--laps N``) as typed world settings; a bad one is a
    one-line ConfigError naming the flag and the key."""
    keys = world_keys()
    world: dict[str, Any] = {}
    for pair in pairs or []:
        key, equals, text = pair.partition("=")
        key = key.strip()
        if not equals or key not in keys:
            raise ConfigError(f"--world {pair}: expected KEY=VALUE with KEY one of {', '.join(keys)}")
        expected, text = keys[key], text.strip()
        try:
            if expected is bool:
                if text.lower() not in ("true", "false", "1", "0", "yes", "no"):
                    raise ValueError(text)
                value: Any = text.lower() in ("true", "1", "yes")
            else:
                value = expected(text)
        except ValueError:
            raise ConfigError(f"--world {pair}: {key} must be {expected.__name__}, got {text!r}") from None
        world[key] = value
    if laps is not None:
        world["laps"] = laps
    return world


def load_preset(preset: str | Path) -> tuple[Camera | None, dict[str, Any]]:
    """A preset's calibration (None when it has none) and its other settings, checked. A
    preset file (``services/common/config.py``) gives its ``[source]`` table over its base's."""
    from services.common.config import is_preset_file, preset_values

    if is_preset_file(preset):
        where = str(preset)
    elif str(preset) in preset_names():
        where = str(PRESET_DIR / f"{preset}.toml")
    else:
        raise ConfigError(f"unknown source preset {str(preset)!r} (available: {', '.join(preset_names())})")
    table = preset_values("source", preset)
    world_fields = world_keys()
    calibration = {key: value for key, value in table.items() if key in CALIBRATION_KEYS}
    settings: dict[str, Any] = {}
    for key, value in table.items():
        if key in CALIBRATION_KEYS:
            continue
        expected = SETTINGS.get(key) or world_fields.get(key)
        if expected is None:
            raise ConfigError(
                f"{where}: unknown key {key!r} (calibration: {', '.join(CALIBRATION_KEYS)}; "
                f"settings: {', '.join([*SETTINGS, *world_fields])})"
            )
        settings[key] = check_setting(key, value, expected, where)
    camera = camera_from_mapping(calibration, where) if calibration else None
    return camera, settings


def parse_spec(spec: str) -> tuple[str, str]:
    """``KIND:TARGET`` split and checked."""
    kind, colon, target = spec.partition(":")
    if not colon or kind not in KINDS or not target:
        raise SourceError(f"source {spec!r}: expected KIND:TARGET with KIND one of {', '.join(KINDS)} (e.g. kitti:PATH, synthetic:0)")
    return kind, target


def open_source(
    spec: str,
    *,
    start: int = 0,
    stop: int | None = None,
    step: int = 1,
    preset: str | Path | None = None,
    calibration: str | Path | Camera | None = None,
    mono: bool = False,
    origin: int | None = None,
    world: Mapping[str, Any] | None = None,
    topics: dict[str, str | float | None] | None = None,
    fov: float | None = None,
) -> FrameSource:
    """Open the source named by ``spec`` (module docstring) with frames ``start:stop:step``.

    ``mono`` drops the right image of stereo sources (less to read for monocular estimators).
    ``origin``: the frame whose pose is the ground truth's origin (default: the first selected).
    ``world``: synthetic world settings (``world_keys()``) over the preset's.
    ``topics``: a ROS bag's settings (BagParams' keys), over the preset's; None values are
    left to the preset.
    ``fov``: the horizontal field of view (degrees) of the pinhole camera assumed for an image
    folder, video or live camera that has no calibration (over the preset's ``fov``; default
    calibration.DEFAULT_FOV_DEG); such a source's ``camera_assumed`` is True.
    Raises SourceError (bad spec or data) or ConfigError (bad preset) with one line naming the file.
    """
    kind, target = parse_spec(spec)
    preset_camera, settings = load_preset(preset) if preset is not None else (None, {})
    if world:
        keys = world_keys()
        for key, value in world.items():
            if key not in keys:
                raise ConfigError(f"world key {key!r} is not a setting of the synthetic world ({', '.join(keys)})")
            if kind != "synthetic":
                raise ConfigError(f"world key {key!r} applies to the synthetic world only, not to {spec}")
            settings[key] = check_setting(key, value, keys[key], "world settings")
    bag = {key: settings.pop(key) for key in BAG_KEYS if key in settings}
    bag.update({key: value for key, value in (topics or {}).items() if value is not None})
    if isinstance(calibration, Camera):
        camera = calibration
    elif calibration is not None:
        camera = read_calibration(calibration)
    else:
        camera = preset_camera
    grey = settings.pop("grey", False)
    fps = settings.pop("fps", None)
    preset_fov = settings.pop("fov", None)
    fov = fov if fov is not None else preset_fov
    source = _open(kind, target, spec, preset, settings, camera, grey, fps, mono, origin, bag,
                   dict(start=start, stop=stop, step=step), fov)
    if kind == "ros2":   # its camera comes with the stream
        return source
    source.camera_assumed = False
    if kind in MONOCULAR_KINDS and source.camera is None:
        width, height = source.image_size
        source.camera = assumed_camera(width, height, DEFAULT_FOV_DEG if fov is None else fov)
        source.camera_assumed = True
    return source


def _open(kind, target, spec, preset, settings, camera, grey, fps, mono, origin, bag, selection, fov) -> FrameSource:
    # A bag may be a recording of the synthetic world: the world's keys then describe what it holds.
    if kind not in ("synthetic", "rosbag") and settings:
        raise ConfigError(f"preset {preset}: key {next(iter(settings))!r} applies to the synthetic world only")
    if kind in ("kitti", "stereo", "images"):
        from services.source import datasets

        loader = {"kitti": datasets.KittiSequence, "stereo": datasets.StereoFolder, "images": datasets.ImageFolder}[kind]
        extra = {"mono": mono} if kind != "images" else {}
        if kind == "kitti":
            extra["origin"] = origin
        return loader(target, camera=camera, fps=fps or datasets.DEFAULT_FPS, grey=grey, **selection, **extra)
    if kind == "video":
        from services.source.datasets import VideoFile

        return VideoFile(target, camera=camera, fps=fps, grey=grey, **selection)
    if kind == "rosbag":
        from services.source.rosbag import RosbagSource

        unknown = sorted(set(bag) - set(BAG_KEYS))
        if unknown:
            raise ConfigError(f"unknown ROS bag setting {unknown[0]!r}")
        return RosbagSource(target, camera=camera, grey=grey, mono=mono, origin=origin, **bag, **selection)
    if kind == "ros2":
        from services.source.ros2 import Ros2Source

        live = {key: value for key, value in bag.items() if key != "image_topic"}
        return Ros2Source(target, camera=camera, grey=grey, mono=mono, fov=fov, **live, **selection)
    if kind == "camera":
        from services.source.camera import LiveCamera

        device: int | str = int(target) if target.isdigit() else target
        return LiveCamera(device, camera=camera, grey=grey, **selection)
    from services.source.synthetic import SyntheticWorld, WorldConfig

    try:
        seed = int(target)
    except ValueError:
        raise SourceError(f"source {spec!r}: the synthetic world's seed must be an integer") from None
    config = WorldConfig(seed=seed, **settings)
    if fps is not None:
        config = dataclasses.replace(config, fps=fps)
    return SyntheticWorld(config, camera=camera, mono=mono, origin=origin, **selection)
