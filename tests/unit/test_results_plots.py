"""Results folders, JSON and config files, the metrics table, and PNG plots."""

import dataclasses
import json
import math
import os
import sys

import cv2
import numpy as np
import pydantic
import pytest

from services.common.errors import GridslamError
from services.evaluation.plots import PlotError, plot_heatmaps, plot_series, plot_trajectories
from services.evaluation.results import (
    ResultsError,
    format_table,
    results_dir,
    write_config,
    write_json,
    write_trajectory_files,
)
from services.evaluation.trajectory import Trajectory, integrate_increments, read_kitti, read_tum


# --- results folders ------------------------------------------------------------------------
def test_results_dir_makes_timestamped_folders_and_moves_latest(tmp_path):
    root = tmp_path / "results"
    first = results_dir(None, root=root)
    second = results_dir(None, root=root)  # same second: must still be a new folder
    assert first.is_dir() and second.is_dir() and first != second
    assert first.parent == root and first.name[:8].isdigit() and first.name[8] == "-"
    latest = root / "latest"
    assert latest.is_symlink() and latest.resolve() == second.resolve()
    assert os.readlink(latest) == second.name  # relative: the folder can be moved as a whole
    assert not [p for p in root.iterdir() if p.name.startswith(".")]


def test_results_dir_uses_out_as_given(tmp_path):
    out = tmp_path / "a" / "b"
    assert results_dir(out, root=tmp_path / "unused") == out
    assert out.is_dir() and not (tmp_path / "unused").exists()


def test_results_dir_not_writable_is_a_clear_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(ResultsError, match=str(blocker)):
        results_dir(blocker / "run")
    with pytest.raises(ResultsError, match="cannot write"):
        results_dir(None, root=blocker)
    assert issubclass(ResultsError, GridslamError)


# --- JSON and config ------------------------------------------------------------------------
def test_write_json_sorts_keys_and_turns_nan_into_null(tmp_path):
    path = write_json(
        tmp_path / "sub" / "metrics.json",
        {"b": math.nan, "a": {"z": np.float32(1.5), "y": np.arange(3), "x": (1, math.inf)}, "c": np.int64(7)},
    )
    text = path.read_text()
    assert json.loads(text) == {"a": {"x": [1, None], "y": [0, 1, 2], "z": 1.5}, "b": None, "c": 7}
    assert text.index('"a"') < text.index('"b"') < text.index('"c"') and "\n  " in text
    with pytest.raises(ResultsError, match="object"):
        write_json(tmp_path / "x.json", {"bad": object()})


def test_write_config_from_pydantic_dataclass_and_dict(tmp_path):
    class Config(pydantic.BaseModel):
        model_config = pydantic.ConfigDict(frozen=True, extra="forbid")
        gain: float = 2.0
        folder: os.PathLike | None = None
        names: tuple[str, ...] = ("a", "b")

    @dataclasses.dataclass
    class Params:
        steps: int = 50

    assert json.loads(write_config(tmp_path / "c1.json", Config(gain=0.2)).read_text()) == {
        "gain": 0.2, "folder": None, "names": ["a", "b"]
    }
    assert json.loads(write_config(tmp_path / "c2.json", Params()).read_text()) == {"steps": 50}
    assert json.loads(write_config(tmp_path / "c3.json", {"k": 1}).read_text()) == {"k": 1}
    with pytest.raises(ResultsError, match="pydantic model"):
        write_config(tmp_path / "c4.json", [1, 2])


def test_trajectory_files_read_back_in_both_conventions(tmp_path):
    traj = integrate_increments([0, 1, 1, 1], [0, 0, 0.1, 0], [0, 0.2, 0.3, -0.1])
    tum, kitti = write_trajectory_files(tmp_path, "egomotion", traj)
    assert tum.name == "egomotion.tum" and kitti.name == "egomotion.kitti.txt"
    assert np.allclose(read_tum(tum).positions, traj.positions)
    camera = read_kitti(kitti)
    # Forward (planar x) is camera z; left (planar y) is camera -x.
    assert np.allclose(camera.positions[:, 2], traj.positions[:, 0])
    assert np.allclose(camera.positions[:, 0], -traj.positions[:, 1])


# --- table ----------------------------------------------------------------------------------
def test_format_table():
    table = format_table([("ATE RMSE (SE(2))", 0.123456, "m"), ("Frames", 205, ""), ("Length", 1233.46, "m"),
                          ("KITTI drift", None, "%"), ("Gap", math.nan, "m")])
    lines = table.splitlines()
    assert lines[0].split("|")[1:4] == [" Metric           ", "  Value ", " Unit "]
    assert len({len(line) for line in lines}) == 1  # columns line up
    cells = [[cell.strip() for cell in line.split("|")[1:4]] for line in lines[2:]]
    assert cells == [["ATE RMSE (SE(2))", "0.1235", "m"], ["Frames", "205", ""], ["Length", "1233.5", "m"],
                     ["KITTI drift", "n/a", "%"], ["Gap", "n/a", "m"]]
    assert set(lines[1]) <= set("|:-")


# --- plots ----------------------------------------------------------------------------------
def read_png(path):
    image = cv2.imread(str(path))
    assert image is not None, f"{path} is not a readable image"
    return image


def test_plot_trajectories_writes_distinct_valid_pngs(tmp_path):
    truth = integrate_increments(np.ones(40), np.zeros(40), np.full(40, 0.08))
    drifted = integrate_increments(np.ones(40), np.zeros(40), np.full(40, 0.1))
    one = read_png(plot_trajectories(tmp_path / "p" / "a.png", {"groundtruth": truth, "egomotion": drifted}, title="t"))
    again = read_png(plot_trajectories(tmp_path / "b.png", {"groundtruth": truth, "egomotion": drifted}, title="t"))
    other = read_png(plot_trajectories(tmp_path / "c.png", {"groundtruth": truth, "egomotion": truth}, title="t"))
    assert one.ndim == 3 and one.shape[2] == 3 and one.shape[0] > 300 and one.shape[1] > 300
    assert np.array_equal(one, again)
    assert one.shape != other.shape or np.any(one != other)
    # Something coloured (not grey) was drawn: the estimate's line.
    assert np.any(np.ptp(one.astype(int), axis=2) > 60)
    empty = read_png(plot_trajectories(tmp_path / "d.png", {"nothing": Trajectory.from_planar([], [], [], [])}))
    assert empty.ndim == 3


def test_plot_series_and_heatmaps(tmp_path):
    frames = np.arange(50)
    first = read_png(plot_series(tmp_path / "s1.png", {"error": (frames, frames * 0.1)}, "frame", "m"))
    second = read_png(plot_series(tmp_path / "s2.png", {"error": (frames, np.sin(frames))}, "frame", "m"))
    assert first.shape == second.shape and np.any(first != second)
    with pytest.raises(PlotError, match="'error': 50 x values but 3"):
        plot_series(tmp_path / "s3.png", {"error": (frames, [1, 2, 3])}, "frame", "m")
    rng = np.random.default_rng(0)
    heat = read_png(plot_heatmaps(tmp_path / "h.png", {"frame 0": rng.random((16, 16)), "frame 9": rng.random((16, 16))}))
    assert heat.shape[1] > heat.shape[0]
    with pytest.raises(PlotError, match="2-D"):
        plot_heatmaps(tmp_path / "h2.png", {"bad": np.zeros(4)})


def test_without_matplotlib_plots_are_skipped_with_one_warning(tmp_path, monkeypatch, caplog):
    """matplotlib is the optional extra `plots` (not in the container image): without it every
    plot function writes nothing and returns None, and the process says so once."""
    from services.evaluation import plots

    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)   # `import` of it raises ImportError
    monkeypatch.setattr(plots, "_missing_said", False)
    truth = integrate_increments(np.ones(5), np.zeros(5), np.zeros(5))
    with caplog.at_level("WARNING", logger=plots.__name__):
        assert plot_trajectories(tmp_path / "t.png", {"groundtruth": truth}) is None
        assert plot_series(tmp_path / "s.png", {"x": ([0, 1], [0, 1])}, "frame", "m") is None
        assert plot_heatmaps(tmp_path / "h.png", {"a": np.zeros((4, 4))}) is None
    assert not list(tmp_path.iterdir())
    assert [r.getMessage() for r in caplog.records] == [
        "matplotlib is not installed: no PNG plots are written (pip install 'gridslam[plots]')"]
