"""A results folder that holds an earlier run: refused in one line, or cleared with --overwrite,
since the services would otherwise resume that run's state instead of starting afresh."""

from __future__ import annotations

import pytest

from services.pipeline.runner import RunError, clear_previous_run


def earlier_run(folder):
    (folder / "logs").mkdir(parents=True)
    for name in ("experience_map.log", "view_templates.log", "view_templates.keyframes", "gridcells.checkpoint.npz",
                 "logs/expmap.log"):
        (folder / name).write_text("earlier run\n")
    for name in ("metrics.json", "notes.txt"):   # results are rewritten by the run; others are the user's
        (folder / name).write_text("{}\n")


def test_a_folder_with_an_earlier_run_is_refused_naming_its_files(tmp_path):
    earlier_run(tmp_path)
    with pytest.raises(RunError) as error:
        clear_previous_run(tmp_path, overwrite=False)
    message = str(error.value)
    assert "\n" not in message and str(tmp_path) in message and "--overwrite" in message
    assert "experience_map.log" in message
    assert (tmp_path / "experience_map.log").exists()


def test_overwrite_removes_the_state_and_logs_and_keeps_the_rest(tmp_path):
    earlier_run(tmp_path)
    clear_previous_run(tmp_path, overwrite=True)
    left = sorted(str(path.relative_to(tmp_path)) for path in tmp_path.rglob("*") if path.is_file())
    assert left == ["metrics.json", "notes.txt"]


def test_an_empty_or_results_only_folder_is_accepted(tmp_path):
    clear_previous_run(tmp_path, overwrite=False)
    (tmp_path / "metrics.json").write_text("{}\n")
    clear_previous_run(tmp_path, overwrite=False)
    assert (tmp_path / "metrics.json").exists()
