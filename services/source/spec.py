"""Open any source from a one-word spec, ``KIND:TARGET``:

    kitti:PATH      KITTI odometry sequence (official layout) or flat clip (datasets.KittiSequence)
    stereo:PATH     stereo pair folder: left/ + right/, or NuBot {k}L.ppm/{k}R.ppm (datasets.StereoFolder)
    images:PATH     folder of monocular images, natural name order (datasets.ImageFolder)
    video:FILE      video file OpenCV decodes (datasets.VideoFile)
    camera:N        live camera N (or a device path / stream URL), newest frame only (camera.LiveCamera)
    synthetic:SEED  procedural world rendered on the fly (synthetic.SyntheticWorld)
    rosbag:PATH     ROS 1 .bag, or ROS 2 bag folder / .db3 / .mcap file (rosbag.RosbagSource; extra `ros`)

A preset (``services/source/presets/<name>.toml``, or a path to such a file) is a flat TOML
table of calibration keys (calibration.py) and source settings (``fps``, ``grey``, the topics of a
ROS bag, and for the synthetic world the fields of ``synthetic.WorldConfig``). An explicit
calibration (a file of our format or a Camera) wins over the preset's, and either wins over the
dataset's own. A preset describes a dataset however it is stored: its bag topics are ignored by
the other kinds (St Lucia is a video and a bag).
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from typing import Any

from services.common.errors import ConfigError
from services.source.calibration import CALIBRATION_KEYS, camera_from_mapping, read_calibration
from services.source.frames import Camera, FrameSource, SourceError

PRESET_DIR = Path(__file__).resolve().parent / "presets"
KINDS = ("kitti", "stereo", "images", "video", "camera", "synthetic", "rosbag")
# The settings of a ROS bag (rosbag.RosbagSource): preset keys, config keys and flags of the same
# names, shared by `gridslam run`, `odometry` and the source service.
BAG_FLAG_HELP = {
    "image_topic": "ROS bag: image topic, sensor_msgs/Image or CompressedImage (default: the bag's only one)",
    "right_image_topic": "ROS bag: right image topic of a stereo pair, matched by stamp",
    "camera_info_topic": "ROS bag: sensor_msgs/CameraInfo topic (default: the image topic's camera_info)",
    "odom_topic": "ROS bag: nav_msgs/Odometry topic (passthrough estimator; ground truth where the run has none)",
    "stereo_tolerance": "ROS bag: seconds between the stamps of a stereo pair, at most (default 0.005)",
}
# Source settings a preset may hold besides the calibration, with their types.
SETTINGS: dict[str, type] = {"fps": float, "grey": bool,
                             **{key: float if key == "stereo_tolerance" else str for key in BAG_FLAG_HELP}}


def add_bag_arguments(parser) -> None:
    """The ROS bag flags (--image-topic, ...) on an argparse parser; the defaults are None."""
    for key, help_text in BAG_FLAG_HELP.items():
        parser.add_argument(f"--{key.replace('_', '-')}", type=float if key == "stereo_tolerance" else str,
                            metavar="S" if key == "stereo_tolerance" else "TOPIC", help=help_text)


def bag_settings(values) -> dict:
    """The ROS bag settings of an argparse namespace or a config model (None where not given)."""
    return {key: getattr(values, key, None) for key in BAG_FLAG_HELP}


def preset_names() -> list[str]:
    """Names of the presets shipped with the project."""
    return sorted(path.stem for path in PRESET_DIR.glob("*.toml"))


def preset_path(preset: str | Path) -> Path:
    """The file of a preset name (``nubot``) or of a path to a TOML file."""
    text = str(preset)
    if text.endswith(".toml") or "/" in text or "\\" in text:
        path = Path(text)
        if not path.is_file():
            raise ConfigError(f"{path}: preset file not found")
        return path
    path = PRESET_DIR / f"{text}.toml"
    if not path.is_file():
        raise ConfigError(f"unknown source preset {text!r} (available: {', '.join(preset_names())})")
    return path


def load_preset(preset: str | Path) -> tuple[Camera | None, dict[str, Any]]:
    """A preset's calibration (None when it has none) and its other settings, checked."""
    from services.source.synthetic import WorldConfig  # the synthetic world's settings are preset keys too

    path = preset_path(preset)
    try:
        with path.open("rb") as stream:
            table = tomllib.load(stream)
    except (OSError, tomllib.TOMLDecodeError) as error:
        raise ConfigError(f"{path}: not a readable TOML preset: {error}") from None
    # The seed comes from the spec (synthetic:SEED), never from a preset.
    world_fields = {field.name: field.type for field in dataclasses.fields(WorldConfig) if field.name != "seed"}
    calibration = {key: value for key, value in table.items() if key in CALIBRATION_KEYS}
    settings: dict[str, Any] = {}
    for key, value in table.items():
        if key in CALIBRATION_KEYS:
            continue
        if key in SETTINGS:
            expected = SETTINGS[key]
        elif key in world_fields:
            expected = {"int": int, "float": float, "bool": bool}.get(str(world_fields[key]), float)
        else:
            raise ConfigError(
                f"{path}: unknown key {key!r} (calibration: {', '.join(CALIBRATION_KEYS)}; "
                f"settings: {', '.join([*SETTINGS, *world_fields])})"
            )
        if expected is str:
            ok = isinstance(value, str)
        else:
            ok = isinstance(value, bool) if expected is bool else isinstance(value, (int, float)) and not isinstance(value, bool)
        if not ok or (expected is int and not isinstance(value, int)):
            raise ConfigError(f"{path}: key {key!r} must be {expected.__name__}, got {value!r}")
        settings[key] = expected(value)
    camera = camera_from_mapping(calibration, str(path)) if calibration else None
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
    topics: dict[str, str | float | None] | None = None,
) -> FrameSource:
    """Open the source named by ``spec`` (module docstring) with frames ``start:stop:step``.

    ``mono`` drops the right image of stereo sources (less to read for monocular estimators).
    ``origin``: the frame whose pose is the ground truth's origin (default: the first selected).
    ``topics``: a ROS bag's settings (BAG_FLAG_HELP's keys), over the preset's; None values are
    left to the preset.
    Raises SourceError (bad spec or data) or ConfigError (bad preset) with one line naming the file.
    """
    kind, target = parse_spec(spec)
    preset_camera, settings = load_preset(preset) if preset is not None else (None, {})
    bag = {key: settings.pop(key) for key in BAG_FLAG_HELP if key in settings}
    bag.update({key: value for key, value in (topics or {}).items() if value is not None})
    if isinstance(calibration, Camera):
        camera = calibration
    elif calibration is not None:
        camera = read_calibration(calibration)
    else:
        camera = preset_camera
    grey = settings.pop("grey", False)
    fps = settings.pop("fps", None)
    # A bag may be a recording of the synthetic world: the world's keys then describe what it holds.
    if kind not in ("synthetic", "rosbag") and settings:
        raise ConfigError(f"preset {preset}: key {next(iter(settings))!r} applies to the synthetic world only")
    selection = dict(start=start, stop=stop, step=step)
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

        unknown = sorted(set(bag) - set(BAG_FLAG_HELP))
        if unknown:
            raise ConfigError(f"unknown ROS bag setting {unknown[0]!r}")
        return RosbagSource(target, camera=camera, grey=grey, mono=mono, origin=origin, **bag, **selection)
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
