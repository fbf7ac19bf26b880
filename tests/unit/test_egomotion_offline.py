"""The offline odometry run: dead reckoning, scores against ground truth and a reference,
and the results folder."""

import json
import math

import numpy as np
import pytest

from services.egomotion import make_estimator
from services.offline.odometry import load_reference, odometry, summary_rows
from services.benchmarks.box_room import pinhole, sequence
from services.evaluation.trajectory import read_tum

CAMERA = pinhole(320, 240, fov_deg=70.0, baseline=0.12)
STEPS = [(0.1, 0.0, 0.0)] * 3 + [(0.1, 0.0, math.radians(5.0))] * 3


@pytest.fixture(scope="module")
def frames():
    return sequence(STEPS, CAMERA, stereo=True, with_odometry=True)


def test_passthrough_reproduces_ground_truth_and_writes_the_folder(frames, tmp_path):
    estimator = make_estimator("passthrough", CAMERA, {"source": "odometry"})
    result = odometry(frames, estimator, out=tmp_path)
    truth = result.metrics["ground_truth"]
    assert truth["ate_se2"]["rmse"] < 1e-9 and truth["frame_errors"]["trans_max"] < 1e-9
    assert result.metrics["path_length_m"] == pytest.approx(0.6)
    assert result.metrics["yaw_total_deg"] == pytest.approx(15.0)
    for name in ("egomotion.tum", "egomotion.kitti.txt", "groundtruth.tum", "increments.csv", "metrics.json", "config.json", "trajectory.png"):
        assert (tmp_path / name).is_file(), name
    estimate = read_tum(tmp_path / "egomotion.tum")
    assert len(estimate) == len(frames) and np.allclose(estimate.positions, result.trajectory.positions, atol=1e-6)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["frames"] == len(frames) and metrics["estimator"] == "passthrough"
    table = dict((row[0], row[1]) for row in summary_rows(result))
    assert table["frames"] == len(frames)


def test_stereo_run_scores_against_ground_truth(frames):
    result = odometry(frames, make_estimator("stereo", CAMERA, {"bucket_size_px": 32}))
    truth = result.metrics["ground_truth"]
    assert truth["ate_se2"]["rmse"] < 0.01
    assert truth["frame_errors"]["rot_max_deg"] < 0.1
    assert result.metrics["fps"] > 0 and result.metrics["low_quality_frames"] == 0


def test_unscaled_runs_also_get_scale_aligned_errors(frames):
    bare = [type(f)(f.seq, f.stamp, f.left, None, CAMERA, f.ground_truth) for f in frames]
    result = odometry(bare, make_estimator("mono", CAMERA, {"scale_source": "none", "bucket_size_px": 32}))
    assert not result.scaled
    truth = result.metrics["ground_truth"]
    aligned = truth["frame_errors_scale_aligned"]
    assert aligned["scale"] == pytest.approx(0.1, rel=0.05)  # unit steps, 0.1 m true
    assert aligned["trans_median"] < 0.01 < truth["frame_errors"]["trans_median"]


def test_reference_from_libviso2_table(shared_data):
    reference = load_reference(shared_data / "nubot_scene1" / "libviso2_egomotion.csv")
    assert len(reference) == 205 and reference.path_length() == pytest.approx(39.4, abs=0.05)
