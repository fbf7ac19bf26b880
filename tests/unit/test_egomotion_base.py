"""Conventions, parameters, presets and the estimator factory of services/egomotion."""

import math

import numpy as np
import pytest

from services.common.errors import ConfigError
from services.egomotion import (
    ESTIMATORS,
    EstimatorConfigError,
    egomotion_config,
    estimator_params,
    make_estimator,
    preset_names,
)
from services.common.geometry import (
    increment_from_transform,
    invert_transform,
    transform_from_increment,
    transform_from_rt,
)
from services.benchmarks.box_room import pinhole
from services.evaluation.trajectory import Trajectory, camera_to_planar, planar_increments


def test_increment_round_trip_and_direction():
    transform = transform_from_increment(0.3, -0.05, math.radians(10))
    forward, left, yaw = increment_from_transform(transform)
    assert (forward, left, math.degrees(yaw)) == pytest.approx((0.3, -0.05, 10.0), abs=1e-12)
    # A counter-clockwise turn moves a point straight ahead to the camera's right (+x).
    ahead = transform @ np.array([0.0, 0.0, 5.0, 1.0])
    assert ahead[0] > 0
    # Moving forward brings a point ahead closer (p_cur = T p_prev).
    assert (transform_from_increment(1.0, 0.0, 0.0) @ np.array([0.0, 0.0, 5.0, 1.0]))[2] == pytest.approx(4.0)


def test_increments_agree_with_evaluation_convention():
    """Composing camera poses and converting with the evaluation service's camera_to_planar
    and planar_increments gives the increments increment_from_transform reports."""
    rng = np.random.default_rng(3)
    steps = [(rng.uniform(0, 0.5), rng.uniform(-0.1, 0.1), rng.uniform(-0.3, 0.3)) for _ in range(20)]
    poses = [np.eye(4)]
    for step in steps:
        tilt = transform_from_rt(rng.normal(0, 0.01, 3), np.zeros(3))  # small pitch/roll noise
        poses.append(poses[-1] @ invert_transform(transform_from_increment(*step)) @ tilt)
    planar = camera_to_planar(Trajectory.from_matrices(np.arange(len(poses)), np.stack(poses)))
    forward, left, yaw = planar_increments(planar)
    ours = np.array([increment_from_transform(invert_transform(b) @ a) for a, b in zip(poses[:-1], poses[1:])])
    assert np.allclose(ours[:, 0], forward[1:], atol=2e-3)
    assert np.allclose(ours[:, 1], left[1:], atol=2e-3)
    assert np.allclose(ours[:, 2], yaw[1:], atol=2e-3)


def test_unknown_estimator_and_parameters_are_named():
    camera = pinhole(320, 240)
    with pytest.raises(EstimatorConfigError, match="unknown estimator 'orb'"):
        make_estimator("orb", camera)
    with pytest.raises(EstimatorConfigError, match="unknown parameter.*vrot_min"):
        make_estimator("scanline", camera, {"vrot_min": 3})
    with pytest.raises(EstimatorConfigError, match="camera_hz must be a number"):
        make_estimator("scanline", camera, {"camera_hz": "fast"})
    with pytest.raises(EstimatorConfigError, match="max_shift_px must be an integer"):
        make_estimator("scanline", camera, {"max_shift_px": 2.5})
    with pytest.raises(EstimatorConfigError, match="failure_motion"):
        make_estimator("stereo", camera, {"failure_motion": "guess"})


def test_stereo_needs_a_baseline_and_mono_a_camera():
    with pytest.raises(EstimatorConfigError, match="stereo calibration"):
        make_estimator("stereo", None)
    with pytest.raises(EstimatorConfigError, match="stereo calibration"):
        make_estimator("stereo", pinhole(320, 240, baseline=0.0))
    with pytest.raises(EstimatorConfigError, match="intrinsics"):
        make_estimator("mono", None)
    assert make_estimator("scanline", None).name == "scanline"


def loaded(preset=None, config_file=None):
    """The default estimator and every estimator's parameters the preset and the config file give."""
    config = egomotion_config(preset, config_file, environ={})
    return config.estimator, {name: estimator_params(config, name) for name in ESTIMATORS}


def test_presets_load_and_build_every_estimator():
    assert set(preset_names()) >= {"nubot", "kitti", "stlucia", "synthetic"}
    camera = pinhole(640, 480)
    for preset in preset_names():
        default, params = loaded(preset)
        assert default in ESTIMATORS
        for name in ESTIMATORS:
            assert make_estimator(name, camera, params[name]).name == name
    # St Lucia keeps OpenRatSLAM's published values.
    _, params = loaded("stlucia")
    assert params["scanline"]["vtrans_scaling"] == 1000.0 and params["scanline"]["camera_fov_deg"] == 53.0


def test_config_file_overrides_preset_and_bad_files_name_themselves(tmp_path):
    good = tmp_path / "mine.toml"
    good.write_text('estimator = "scanline"\n[scanline]\nmax_shift_px = 7\n')
    default, params = loaded("nubot", good)
    assert default == "scanline"
    assert params["scanline"]["max_shift_px"] == 7 and params["scanline"]["vtrans_scaling"] == 77.0
    bad = tmp_path / "bad.toml"
    bad.write_text('estimator = "stereo"\n[sterio]\nx = 1\n')
    with pytest.raises(ConfigError, match=r"\[egomotion\] sterio: Extra inputs are not permitted \(from .*bad.toml\)"):
        loaded(None, bad)
    bad.write_text("[stereo]\nmin_inliers = 'many'\n")
    with pytest.raises(ConfigError, match=r"\[egomotion.stereo\] min_inliers: Input should be a valid integer.*'many'.*bad.toml"):
        loaded(None, bad)
    whole = tmp_path / "run.toml"   # a whole run's config file: its [egomotion] table
    whole.write_text('[source]\nlaps = 2\n[egomotion]\nestimator = "scanline"\ninstances = 2\n'
                     '[egomotion.scanline]\nmax_shift_px = 7\n')
    assert loaded("nubot", whole) == (default, params)
    with pytest.raises(ConfigError, match="config file not found"):
        loaded(None, tmp_path / "absent.toml")
    with pytest.raises(ConfigError, match="unknown preset 'mars' for egomotion"):
        loaded("mars")


def test_every_parameter_is_documented():
    """docs/egomotion.md has a row for every estimator parameter (so the docs cannot go stale)."""
    import dataclasses
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs" / "egomotion.md").read_text()
    missing = [
        f"{name}.{field.name}"
        for name, (_, params) in ESTIMATORS.items()
        for field in dataclasses.fields(params)
        if f"`{field.name}`" not in text
    ]
    assert not missing, f"undocumented parameters: {missing}"


def test_every_parameter_is_declared_with_help_and_a_value_out_of_bounds_names_its_key(tmp_path):
    """Each estimator parameter has help and, for a number, bounds (services.common.settings.setting);
    the [egomotion.<estimator>] tables derived from them refuse a value outside them in one
    line naming the key, and so does make_estimator."""
    import dataclasses

    bounded = ("ge", "gt", "le", "lt")
    for name, (_, params) in ESTIMATORS.items():
        for field in dataclasses.fields(params):
            assert field.metadata.get("help"), f"{name}.{field.name} has no help"
            if field.type in ("int", "float", "float | None"):
                assert any(field.metadata.get(bound) is not None for bound in bounded), f"{name}.{field.name} has no bounds"
            if field.type == "str":
                assert field.metadata.get("choices"), f"{name}.{field.name} has no choices"
    path = tmp_path / "bad.toml"
    cases = [("stereo", "ransac_iterations", 0, "greater than or equal to 1"),
             ("stereo", "retry_below_quality", 1.5, "less than or equal to 1"),
             ("scanline", "camera_hz", 0.0, "greater than 0"),
             ("mono", "scale_source", "sky", "'auto', 'odometry', 'ground' or 'none'"),
             ("passthrough", "noise_yaw", -0.1, "greater than or equal to 0"),
             ("mono", "sigma_yaw", -1.0, "greater than or equal to 0")]
    for name, key, value, says in cases:
        path.write_text(f"[egomotion.{name}]\n{key} = {value!r}\n".replace("'", '"'))
        with pytest.raises(ConfigError) as raised:
            egomotion_config(config_file=path, environ={})
        message = str(raised.value)
        assert "\n" not in message and message.startswith(f"[egomotion.{name}] {key}: ") and says in message, message
        assert str(path) in message
        with pytest.raises(EstimatorConfigError, match=rf"^{name} parameters: invalid {key} = "):
            make_estimator(name, pinhole(320, 240, baseline=0.1), {key: value})
    # A file of the table's own shape (no [egomotion] around it, as a preset) is checked alike.
    path.write_text("[stereo]\nransac_iterations = -3\n")
    with pytest.raises(ConfigError, match=r"^\[egomotion.stereo\] ransac_iterations: Input should be greater than or equal to 1"):
        egomotion_config(config_file=path, environ={})
