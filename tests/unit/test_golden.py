"""The golden results (tests/golden/) and README.md agree, and a run is compared with them as
the golden files say: counts equal, accuracy figures within 2 %."""

import json

import pytest

from services.common.errors import DataError
from services.evaluation.results import format_value
from tests import golden
from tests.netutil import REPO

README = (REPO / "README.md").read_text()


def test_the_readmes_demo_table_states_the_golden_figures():
    rows = golden.readme_rows(README)
    figures = golden.load("demo")["figures"]
    assert len(figures) >= 20
    for metric, value in figures.items():
        assert rows.get(metric) == format_value(value), (metric, rows.get(metric), value)
    assert not any(metric.startswith("map: latency") or metric == "map: throughput" for metric in rows)


def test_the_readmes_nubot_row_states_the_golden_figures():
    figures = golden.load("nubot")["figures"]
    row = next(line for line in README.splitlines() if line.startswith("| NuBot scene 1, left images"))
    assert golden.load("nubot")["command"] in row
    assert f"| {figures['revisit frames joined by a confirmed closure']} of {len(golden.NUBOT_REVISITS)} " in row
    assert f"| {figures['closures between frames the loop does not mark']}: " in row
    assert f"an ATE of {format_value(figures['egomotion: ATE RMSE (Sim(3)) against LIBVISO2'])} m" in " ".join(README.split())


def test_counts_must_be_equal_and_accuracy_within_the_tolerance():
    want = {"confirmed loop closures": 365, "closures accepted / rejected / unmeasured by the map": "363 / 2 / 0",
            "map: ATE RMSE (SE(2))": 0.01}
    assert golden.differences(want, dict(want)) == []
    assert golden.differences(want, {**want, "map: ATE RMSE (SE(2))": 0.01 * (1 + 0.9 * golden.GOLDEN_TOLERANCE)}) == []
    for changed in ({"confirmed loop closures": 366}, {"closures accepted / rejected / unmeasured by the map": "362 / 3 / 0"},
                    {"map: ATE RMSE (SE(2))": 0.01 * (1 + 1.1 * golden.GOLDEN_TOLERANCE)},
                    {"map: ATE RMSE (SE(2))": 0.01 * (1 - 1.1 * golden.GOLDEN_TOLERANCE)}):
        (problem,) = golden.differences(want, {**want, **changed})
        assert problem.startswith(next(iter(changed)))
    (missing,) = golden.differences(want, {k: v for k, v in want.items() if k != "confirmed loop closures"})
    assert missing.startswith("confirmed loop closures: golden 365, this run —")


def test_the_figures_held_are_the_tables_rows_that_do_not_depend_on_the_load(tmp_path):
    with pytest.raises(DataError, match="metrics.json: not found"):
        golden.figures("demo", tmp_path)
    closures = {"accepted": 3, "rejected": 1, "unmeasured": 0, "accepted_true": 3, "accepted_false": 0,
                "rejected_true": 1, "rejected_false": 0}
    stage = {"frames": 40, "ate_se2": {"rmse": 0.02}, "ate_sim3": {"rmse": 0.019}, "endpoint": {"percent_of_path": 0.1}}
    metrics = {"summary": {"frames_sent": 40, "wall_time_s": 3.5, "groundtruth_path_length_m": 4.0, "view_templates": 7,
                           "experiences": 9, "loop_closures": [{"frame": 30, "matched_frame": 2}] * 4, "map_closures": closures},
               "stages": {"gridcells": {**stage, "latency_ms": {"p50": 20.0, "p99": 40.0}, "throughput_fps": 12.0},
                          "map": stage},
               "services": {"expmap": {"decode_errors": 0, "gaps": 0, "restarts": 0}}}
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    figures = golden.figures("demo", tmp_path)
    assert figures == {"frames sent": 40, "ground-truth path": 4.0, "view templates": 7, "experiences": 9,
                       "confirmed loop closures": 4, "closures accepted / rejected / unmeasured by the map": "3 / 1 / 0",
                       "closures accepted: true / false": "3 / 0", "closures rejected: true / false": "1 / 0",
                       **{f"{name}: {metric}": value for name in ("gridcells", "map")
                          for metric, value in (("frames", 40), ("ATE RMSE (SE(2))", 0.02), ("ATE RMSE (Sim(3))", 0.019),
                                                ("endpoint error", 0.1))}}
