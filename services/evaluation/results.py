"""Results folders and what goes in them: JSON, the resolved config, trajectory files,
and the Metric | Value | Unit table commands print (the layout of kiss-icp's pipeline:
results/<timestamp>/ with a `latest` link beside it)."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from services.common.errors import GridslamError
from services.evaluation.trajectory import Trajectory, planar_to_camera, write_kitti, write_tum

log = logging.getLogger(__name__)

LATEST = "latest"


class ResultsError(GridslamError):
    """A results folder cannot be created or written (the message names it)."""


def _ensure_writable(folder: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        # os.access lies for root and on some network file systems: really write.
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".write-test-"):
            pass
    except OSError as error:
        raise ResultsError(f"{folder}: cannot write results there ({error.strerror or error})") from None


def results_dir(out: Path | None = None, root: Path = Path("results")) -> Path:
    """The folder a run writes into.

    With `out`, that folder (created if needed). Otherwise a new `root/<YYYYmmdd-HHMMSS>`
    (suffixed -1, -2, … if taken) and a `root/latest` symlink to it, replaced atomically
    so that a reader never sees it missing. Raises ResultsError when it is not writable.
    """
    if out is not None:
        out = Path(out)
        _ensure_writable(out)
        return out
    root = Path(root)
    _ensure_writable(root)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    for attempt in range(1000):
        folder = root / (stamp if attempt == 0 else f"{stamp}-{attempt}")
        try:
            folder.mkdir()  # not exist_ok: two runs started in the same second get two folders
            break
        except FileExistsError:
            continue
        except OSError as error:
            raise ResultsError(f"{folder}: cannot create the results folder ({error.strerror or error})") from None
    else:
        raise ResultsError(f"{root}: no free results folder name for {stamp}")
    _point_latest(root, folder)
    log.info("results go to %s", folder)
    return folder


def _point_latest(root: Path, folder: Path) -> None:
    link = root / LATEST
    temporary = root / f".{LATEST}-{uuid.uuid4().hex}"
    try:
        temporary.symlink_to(folder.name, target_is_directory=True)
        os.replace(temporary, link)  # atomic rename over the old link
    except OSError as error:
        log.warning("could not point %s at %s: %s", link, folder, error)
        temporary.unlink(missing_ok=True)


def to_jsonable(obj: Any) -> Any:
    """Plain JSON values: numpy scalars and arrays, paths, tuples, dataclasses and pydantic
    models converted; NaN and infinities become null (JSON has no NaN)."""
    if hasattr(obj, "model_dump"):
        return to_jsonable(obj.model_dump(mode="json"))
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return to_jsonable(dataclasses.asdict(obj))
    if isinstance(obj, dict):
        return {str(key): to_jsonable(value) for key, value in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [to_jsonable(value) for value in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    if obj is None or isinstance(obj, (str, int, bool)):
        return obj
    raise ResultsError(f"cannot write a {type(obj).__name__} as JSON")


def _write_text_atomically(path: Path, text: str) -> Path:
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
        temporary.write_text(text)
        os.replace(temporary, path)
    except OSError as error:
        raise ResultsError(f"{path}: cannot write ({error.strerror or error})") from None
    return path


def write_json(path, obj) -> Path:
    """Write `obj` as JSON: sorted keys, indented, NaN as null, atomically."""
    text = json.dumps(to_jsonable(obj), sort_keys=True, indent=2, allow_nan=False)
    return _write_text_atomically(Path(path), text + "\n")


def write_config(path, model_or_dict) -> Path:
    """Write the resolved config: a pydantic model (model_dump(mode="json")), a dataclass
    or a dict."""
    if not (hasattr(model_or_dict, "model_dump") or isinstance(model_or_dict, dict) or dataclasses.is_dataclass(model_or_dict)):
        raise ResultsError(f"{path}: a config must be a pydantic model, a dataclass or a dict, got {type(model_or_dict).__name__}")
    return write_json(path, model_or_dict)


def write_trajectory_files(folder, stem: str, traj: Trajectory) -> tuple[Path, Path]:
    """Write `<stem>.tum` (the planar-world poses as they are) and `<stem>.kitti.txt` (the same
    poses in KITTI's camera convention, x right, y down, z forward, so KITTI tools plot them
    the right way up). Errors between two trajectories are the same in either file.
    Returns both paths."""
    folder = Path(folder)
    try:
        tum = write_tum(folder / f"{stem}.tum", traj)
        kitti = write_kitti(folder / f"{stem}.kitti.txt", planar_to_camera(traj))
    except OSError as error:
        raise ResultsError(f"{folder}: cannot write {stem} trajectory ({error.strerror or error})") from None
    return tum, kitti


def format_value(value: Any) -> str:
    """A number as a table shows it: 4 significant digits, one decimal from 1000 up."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return f"{value:.1f}" if abs(value) >= 1000 else f"{value:.4g}"
    return str(value)


def format_table(rows: list[tuple[str, Any, str]]) -> str:
    """The Metric | Value | Unit table commands print at the end of a run (Markdown, so it
    can be pasted into docs as it is). Values are right-aligned."""
    header = ("Metric", "Value", "Unit")
    cells = [(str(metric), format_value(value), str(unit)) for metric, value, unit in rows]
    widths = [max(len(row[column]) for row in [header, *cells]) for column in range(3)]
    widths = [max(width, 3) for width in widths]

    def line(row: tuple[str, str, str]) -> str:
        return f"| {row[0]:<{widths[0]}} | {row[1]:>{widths[1]}} | {row[2]:<{widths[2]}} |"

    rule = f"|:{'-' * (widths[0] + 1)}|{'-' * (widths[1] + 1)}:|:{'-' * (widths[2] + 1)}|"
    return "\n".join([line(header), rule, *(line(row) for row in cells)])
