"""A run's results folder as `run.mcap` again (`gridslam export mcap RESULTS_DIR`): its TUM
files, its map journal replayed frame by frame, the closures of metrics.json and the camera
images read again from the run's source (config.json), written by services/ros/mcap_export.py."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Iterator

import numpy as np

from services.common.errors import DataError, GridslamError
from services.common.layout import MAP_LOG
from services.common.observe import link_kind
from services.evaluation.trajectory import read_tum
from services.expmap.export import read_log
from services.expmap.graph import ExperienceMap
from services.pipeline.runner import ASSUMED, RunConfig
from services.ros.mcap_export import MARKER_PERIOD_S, MCAP_NAME, STAGE_FILES, RunContent, write_run_mcap
from services.ros2wire.messages import CAMERA_MAX_WIDTH, camera_jpeg
from services.source.spec import bag_settings, open_source

log = logging.getLogger(__name__)


class McapExportError(DataError):
    """A results folder that cannot be exported (the message names the file)."""


def content_from_folder(folder: Path, images: bool = True) -> RunContent:
    """The content of a run from its results folder: the TUM files of the stages, the map
    journal replayed frame by frame, the closures of metrics.json, and the camera images read
    again from the run's source (config.json) when `images` and the source is still there.
    The grid-cell activity is not in a results folder, so an export has none."""
    folder = Path(folder)
    if not folder.is_dir():
        raise McapExportError(f"{folder}: no such results folder")
    trajectories = {stage: read_tum(folder / f"{name}.tum") for stage, name in STAGE_FILES.items()
                    if (folder / f"{name}.tum").is_file()}
    if not trajectories:
        raise McapExportError(f"{folder}: no trajectory (*.tum) of a gridslam run")
    config = _read_json(folder / "config.json")
    map_log = _map_log(folder)
    frame_stamps = {step.frame: step.stamp for step in map_log.steps} if map_log is not None else {}
    closures = []
    for closure in (_read_json(folder / "metrics.json").get("summary", {}).get("loop_closures") or []):
        if closure.get("frame") in frame_stamps:
            closures.append((frame_stamps[closure["frame"]], closure))
    content = RunContent(trajectories=trajectories, map_updates=_journal_updates(map_log) if map_log is not None else (),
                         closures=closures, metadata={"source": str(config.get("source", "")), "exported_from": str(folder)})
    if images and config.get("source"):
        content.images, content.camera_model = _source_images(config)
    return content


def _read_json(path: Path) -> dict:
    if not path.is_file():
        return {}
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise McapExportError(f"{path}: not readable JSON ({error})") from None


def _map_log(folder: Path):
    if not (folder / MAP_LOG).is_file():
        return None
    return read_log(folder / MAP_LOG)


def _journal_updates(map_log) -> Iterator[tuple[float, list, list]]:
    """The map after its frames, replayed from its journal: the map as it was published every
    MARKER_PERIOD_S of the run's time, and the final map (as `map export` writes it) after the
    last frame."""
    experience_map = ExperienceMap(map_log.params)
    last = None
    for index, step in enumerate(map_log.steps):
        step.apply(experience_map)
        final = index == len(map_log.steps) - 1
        if last is None or step.stamp - last >= MARKER_PERIOD_S or final:
            state = experience_map.snapshot()
            poses = experience_map.final_poses() if final else state.poses
            last = step.stamp
            yield (step.stamp, [(i, float(x), float(y)) for i, (x, y, _) in enumerate(poses)],
                   [(link.source, link.target, link_kind(link.loop_closure, link.accepted)) for link in state.links])


def _source_images(config: dict):
    """The run's left camera images again, from its source (the run's config.json); ((), None)
    when it cannot be read."""
    from pydantic import ValidationError

    try:
        run = RunConfig.model_validate({key: value for key, value in config.items() if key != ASSUMED})
    except ValidationError as error:
        log.warning("camera images left out: config.json is not a run's configuration (%s)",
                    str(error).splitlines()[0])
        return (), None
    if run.source.startswith("camera:"):
        log.warning("camera images left out: the run's source %s is a live camera", run.source)
        return (), None
    stop = run.start + run.n_frames * run.step if run.n_frames else None
    try:
        frames = open_source(run.source, start=run.start, stop=stop, step=run.step, preset=run.preset,
                             calibration=run.calibration, mono=True, topics=bag_settings(run), fov=run.fov)
    except GridslamError as error:   # a moved dataset: the export goes on without images
        log.warning("camera images left out: the run's source %s cannot be read again (%s)", run.source, error)
        return (), None
    first = frames[0]
    scale = min(1.0, CAMERA_MAX_WIDTH / first.left.shape[1])   # as camera_jpeg scales the image
    camera = frames.camera
    model = None if camera is None else (camera.fx * scale, camera.fy * scale, camera.cx * scale, camera.cy * scale,
                                         round(first.left.shape[1] * scale), round(first.left.shape[0] * scale))

    def images():
        with frames:
            for frame in frames:
                yield frame.stamp, camera_jpeg(frame.left, _encoding(frame.left))[0]

    return images(), model


def _encoding(image: np.ndarray) -> str:
    return "bgr8" if image.ndim == 3 else "mono8"


def export_mcap(folder: Path, out: Path | None = None, images: bool = True) -> tuple[Path, dict[str, int]]:
    """`gridslam export mcap`: write FOLDER/run.mcap (or `out`) again from the results folder."""
    path = Path(out) if out is not None else Path(folder) / MCAP_NAME
    return path, write_run_mcap(path, content_from_folder(folder, images))
