"""Every config-file key and environment variable that exists still works: the keys of each
table of a --config file (and of a preset file's tables), the GRIDSLAM_<SECTION>_<FIELD>
variables derived from them, and the variables read on their own (the flags: test_cli_flags.py).
A key is checked by loading a config file that sets it, a variable by loading with it set."""

import dataclasses
import math
from pathlib import Path

import pytest

from services.common.config import env_values, load_config
from services.common.errors import ConfigError

# Every key of every table, as it is today (section → keys). A key renamed later keeps working.
KEYS = {
    "runtime": "mode connect listen multicast_scouting robot zenoh_config cfg",
    "source": (
        "source preset calibration fov mono start origin stop step rate window adaptive_window live_window ack_topic "
        "resend_after resend_acknowledged exit_at_end loop wait_for resume image_topic right_image_topic "
        "camera_info_topic odom_topic stereo_tolerance length breadth corridor_width wall_height camera_height laps "
        "speed frames_per_lap fps wander pillar_spacing noise exposure_jitter layout max_turn_deg lamps_off "
        "light_variation light_period"),
    "gridcells": (
        "integrator decoder step modules heading velocity_scale typical_speed neurons direction_sigma activity_every "
        "activity_size checkpoint"),
    "loopclosure": (
        "place_recognition crop width height normalisation shift_range match_threshold fov_deg matcher candidates "
        "index_rows window min_votes tolerance recent_frames confirm_run closure geometry scanline_translation_sigma "
        "scanline_heading_sigma geometry_params keyframe_store_mb map localize store bow_candidates "
        "bow_recent_candidates bow_min_inliers bow_place_inliers bow_vocabulary sequence_width sequence_height "
        "sequence_patch sequence_length sequence_min_speed sequence_max_speed sequence_speeds sequence_new_place "
        "sequence_match_threshold sequence_uniqueness sequence_candidates"),
    "expmap": (
        "new_experience_distance optimizer closure correction relax_passes relax_every_frame "
        "odometry_translation_sigma odometry_heading_sigma odometry_turn_sigma odometry_translation_floor "
        "odometry_heading_floor snap_translation_sigma snap_heading_sigma mono_scale_sigma robust_kernel kernel_width "
        "closure_gate closure_iterations join_closures join_gate store checkpoint_updates checkpoint_frames out map localize"),
    "viewer": "allow_remote http rate_hz map_rate_hz image_rate_hz max_points camera_width max_clients fleet",
    "foxglove": "allow_remote host port map_rate_hz backlog history fleet",
    "ros2": "path_rate_hz map_rate_hz ros_domain_id ros_namespace ros_distro ros2_keys",
    "run": (
        "source egomotion integrator decoder step_source modules heading preset calibration fov camera_height "
        "config_file n_frames start step listen connect robot window egomotion_instances mapping closure "
        "map_optimizer map localize place_recognition view stall_timeout world mcap foxglove ros2 image_topic "
        "right_image_topic camera_info_topic odom_topic stereo_tolerance ros_domain_id ros_namespace ros_distro "
        "ros2_keys"),
}
# [egomotion]: the estimator, how the instances share the frames, one table per estimator.
EGOMOTION_KEYS = "estimator instances shard_block"
ESTIMATOR_KEYS = {
    "scanline": (
        "sigma_translation sigma_translation_floor sigma_yaw sigma_yaw_per_m sigma_yaw_floor sigma_failure_m "
        "sigma_failure_rad vtrans_image_x_min vtrans_image_x_max vtrans_image_y_min vtrans_image_y_max "
        "vrot_image_x_min vrot_image_x_max vrot_image_y_min vrot_image_y_max camera_fov_deg camera_hz vtrans_scaling "
        "vtrans_max max_shift_px subpixel equiangular"),
    "stereo": (
        "sigma_translation sigma_translation_floor sigma_yaw sigma_yaw_per_m sigma_yaw_floor sigma_failure_m "
        "sigma_failure_rad fast_threshold bucket_size_px features_per_bucket klt_window_px stereo_pyramid_levels "
        "track_pyramid_levels forward_backward_px affine_brightness stereo_forward_backward_px max_row_error_px "
        "min_disparity_px ransac_reprojection_px ransac_iterations min_inliers retry_below_quality quality_inliers "
        "predict carry_tracks carried_stereo_pyramid_levels failure_motion"),
    "mono": (
        "sigma_translation sigma_translation_floor sigma_yaw sigma_yaw_per_m sigma_yaw_floor sigma_failure_m "
        "sigma_failure_rad fast_threshold bucket_size_px features_per_bucket klt_window_px pyramid_levels "
        "forward_backward_px ransac_threshold_px min_inliers min_parallax_px quality_inliers scale_source "
        "camera_height_m ground_margin_px ground_max_tilt_deg ground_inlier_fraction ground_min_points scale_window "
        "failure_motion"),
    "passthrough": (
        "sigma_translation sigma_translation_floor sigma_yaw sigma_yaw_per_m sigma_yaw_floor sigma_failure_m "
        "sigma_failure_rad source noise_forward noise_left noise_yaw seed"),
}
# [loopclosure] geometry_params: the closure geometry's keys.
GEOMETRY_KEYS = (
    "features query_features grid pyramid_levels fast_threshold ratio max_distance stereo_window_px "
    "stereo_pyramid_levels stereo_candidates stereo_forward_backward_px max_row_error_px min_disparity_px ransac_px "
    "ransac_iterations mono_threshold_px min_inliers min_inlier_ratio min_parallax_px max_translation_m max_yaw_deg "
    "max_tilt_deg max_height_m pixel_sigma disparity_sigma floor_translation_m floor_yaw_deg floor_direction_deg")
CALIBRATION_KEYS = "fx fy cx cy baseline width height"
# Variables read on their own, beside GRIDSLAM_<SECTION>_<FIELD> of the tables above.
ENVIRONMENT = ("GRIDSLAM_FFT GRIDSLAM_CACHE GRIDSLAM_EGOMOTION_ESTIMATOR GRIDSLAM_EGOMOTION_INSTANCES "
               "GRIDSLAM_EGOMOTION_SHARD_BLOCK GRIDSLAM_SOURCE_PRESET GRIDSLAM_EGOMOTION_PRESET GRIDSLAM_GRIDCELLS_PRESET "
               "GRIDSLAM_LOOPCLOSURE_PRESET GRIDSLAM_EXPMAP_PRESET GRIDSLAM_VIEWER_PRESET GRIDSLAM_FOXGLOVE_PRESET "
               "GRIDSLAM_ROS2_PRESET GRIDSLAM_FLEETMAP_PRESET")


def model_of(section: str):
    from services.common.runtime import RuntimeConfig
    from services.expmap.service import ExpMapConfig
    from services.gridcells.config import GridCellsConfig
    from services.loopclosure.service import LoopClosureConfig
    from services.pipeline.runner import RunConfig
    from services.ros.foxglove import FoxgloveConfig
    from services.ros.node import Ros2Config
    from services.source.service import SourceConfig
    from services.viewer.config import ViewerConfig

    return {"runtime": RuntimeConfig, "source": SourceConfig, "gridcells": GridCellsConfig,
            "loopclosure": LoopClosureConfig, "expmap": ExpMapConfig, "viewer": ViewerConfig,
            "foxglove": FoxgloveConfig, "ros2": Ros2Config, "run": RunConfig}[section]


def toml_value(value):
    """``value`` written as TOML, or None where TOML cannot hold it (None)."""
    if value is None:
        return None
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(float(value)) if isinstance(value, float) and math.isfinite(value) else str(value)
    if isinstance(value, (list, tuple)):
        items = [toml_value(item) for item in value]
        return None if None in items else "[" + ", ".join(items) + "]"
    if isinstance(value, dict):
        return "{}" if not value else None
    return '"' + str(value).replace("\\", "\\\\") + '"'


REQUIRED = {"source": {"source": "synthetic:0"}, "run": {"source": "synthetic:0"}}


# Keys read in an older spelling (a test below loads each): section → key.
OLD_SPELLINGS = {"loopclosure": {"geometry_params"}}   # now geometry_<key> (GEOMETRY_KEYS)


def keys(section: str) -> list[str]:
    return [key for key in KEYS[section].split() if key not in OLD_SPELLINGS.get(section, ())]


@pytest.mark.parametrize("section", sorted(KEYS))
def test_every_key_of_every_table_is_read(section, tmp_path):
    model = model_of(section)
    unknown = sorted(set(keys(section)) - set(model.model_fields))
    assert unknown == [], f"[{section}] keys gone: {unknown}"
    for key in keys(section):
        field = model.model_fields[key]
        value = REQUIRED.get(section, {}).get(key, field.get_default(call_default_factory=True))
        text = toml_value(value)
        if text is None:
            continue   # only None (or a non-empty table) as default: no TOML for it, the field's presence checked above
        path = tmp_path / f"{section}_{key}.toml"
        path.write_text(f"[{section}]\n{key} = {text}\n" + "".join(
            f"{k} = {toml_value(v)}\n" for k, v in REQUIRED.get(section, {}).items() if k != key))
        config = load_config(model, section, config_file=path, environ={})
        assert key in config.model_fields_set, (section, key)


@pytest.mark.parametrize("section", sorted(KEYS))
def test_every_field_has_its_environment_variable(section):
    model = model_of(section)
    for key in keys(section):
        variable = f"GRIDSLAM_{section}_{key}".upper()
        assert key in env_values(section, model, {variable: "x"}), variable


def test_the_egomotion_tables(tmp_path):
    from services.egomotion import ESTIMATORS, resolve_estimator, resolve_sharding

    for name, keys in ESTIMATOR_KEYS.items():
        params = ESTIMATORS[name][1]
        declared = {f.name: f.default for f in dataclasses.fields(params)}
        assert set(keys.split()) <= set(declared), name
        path = tmp_path / f"{name}.toml"
        lines = [f"{key} = {toml_value(declared[key])}" for key in keys.split() if toml_value(declared[key]) is not None]
        path.write_text(f'[egomotion]\nestimator = "{name}"\ninstances = 2\nshard_block = 3\n[egomotion.{name}]\n'
                        + "\n".join(lines) + "\n")
        chosen, values = resolve_estimator(config_file=path, environ={})
        assert chosen == name and set(values) == {line.split(" = ")[0] for line in lines}
        sharding, block = resolve_sharding(name, config_file=path, environ={})
        assert (sharding.instances, sharding.shard_block) == (2, 3)
    assert set(EGOMOTION_KEYS.split()) == {"estimator", *(f.name for f in dataclasses.fields(sharding))}
    from services.egomotion import EgomotionConfig
    assert set(EgomotionConfig.model_fields) == {*EGOMOTION_KEYS.split(), *ESTIMATOR_KEYS}


def test_the_closure_geometry_keys(tmp_path):
    from services.loopclosure.geometry import GeometryParams
    from services.loopclosure.service import LoopClosureConfig

    declared = {f.name: f.default for f in dataclasses.fields(GeometryParams)}
    assert set(GEOMETRY_KEYS.split()) <= set(declared)
    path = tmp_path / "geometry.toml"
    path.write_text("[loopclosure.geometry_params]\n" + "".join(
        f"{key} = {toml_value(declared[key])}\n" for key in GEOMETRY_KEYS.split()))
    config = load_config(LoopClosureConfig, "loopclosure", config_file=path, environ={})
    assert config.geometry_parameters() == GeometryParams()
    # The older spelling, a table, and the single keys: the same settings, and the same journal header.
    path.write_text("[loopclosure]\ngeometry_features = 300\ngeometry_grid = [4, 3]\n")
    single = load_config(LoopClosureConfig, "loopclosure", config_file=path, environ={})
    path.write_text("[loopclosure.geometry_params]\nfeatures = 300\ngrid = [4, 3]\n")
    table = load_config(LoopClosureConfig, "loopclosure", config_file=path, environ={})
    assert single.geometry_parameters() == table.geometry_parameters() == GeometryParams(features=300, grid=(4, 3))
    header = table.journal_params()
    assert header == single.journal_params() and header["geometry_params"] == {"features": 300, "grid": [4, 3]}
    excluded = {"store", "keyframe_store_mb", "map", "localize"}
    # The header's shape journals have always had: the old keys, the geometry as one table.
    assert set(KEYS["loopclosure"].split()) - excluded <= set(header)
    assert [key for key in header if key.startswith("geometry_") and key != "geometry_params"] == []
    path.write_text("[loopclosure.geometry_params]\nfeaturez = 300\n")
    with pytest.raises(ConfigError, match="geometry_params: unknown key.s. featurez"):
        load_config(LoopClosureConfig, "loopclosure", config_file=path, environ={})


def test_the_calibration_keys(tmp_path):
    from services.source.calibration import read_calibration

    path = tmp_path / "camera.toml"
    values = dict(zip(CALIBRATION_KEYS.split(), (500.0, 501.0, 320.0, 240.0, 0.12, 640, 480), strict=True))
    path.write_text("".join(f"{key} = {value}\n" for key, value in values.items()))
    assert dataclasses.asdict(read_calibration(path)) == values


def test_the_variables_read_on_their_own(monkeypatch, tmp_path):
    from services.cli.service import SERVICES, service_defaults
    from services.egomotion import resolve_estimator, resolve_sharding
    from services.gridcells.calibration import cache_dir
    from services.gridcells.network import fft_backend

    variables = set(ENVIRONMENT.split())
    monkeypatch.setenv("GRIDSLAM_FFT", "scipy")
    assert fft_backend() == "scipy"
    monkeypatch.setenv("GRIDSLAM_FFT", "neither")
    with pytest.raises(ConfigError, match="GRIDSLAM_FFT"):
        fft_backend()
    monkeypatch.setenv("GRIDSLAM_CACHE", str(tmp_path))
    assert cache_dir() == tmp_path
    assert resolve_estimator(environ={"GRIDSLAM_EGOMOTION_ESTIMATOR": "mono"})[0] == "mono"
    sharding, block = resolve_sharding("stereo", environ={"GRIDSLAM_EGOMOTION_INSTANCES": "3",
                                                          "GRIDSLAM_EGOMOTION_SHARD_BLOCK": "6"})
    assert (sharding.instances, block) == (3, 6)
    for name in SERVICES:
        variable = f"GRIDSLAM_{name.upper()}_PRESET"
        assert variable in variables, variable
        assert service_defaults(name, {variable: "nubot"})["preset"] == "nubot"
    checked = {"GRIDSLAM_FFT", "GRIDSLAM_CACHE", "GRIDSLAM_EGOMOTION_ESTIMATOR", "GRIDSLAM_EGOMOTION_INSTANCES",
               "GRIDSLAM_EGOMOTION_SHARD_BLOCK", *(f"GRIDSLAM_{name.upper()}_PRESET" for name in SERVICES)}
    assert variables == checked


def test_a_key_that_never_existed_is_refused(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[gridcells]\ndecoderr = \"fft\"\n")
    from services.gridcells.config import GridCellsConfig
    with pytest.raises(ConfigError, match="decoderr"):
        load_config(GridCellsConfig, "gridcells", config_file=path, environ={})


def test_a_table_that_never_existed_is_refused_by_every_reader_of_the_file(tmp_path):
    """A mistyped table is refused, whichever service reads the file (each reads its own table),
    and gridslam odometry's --config too; the tables are the services gridslam service starts."""
    from services.cli.service import SERVICES
    from services.common.config import SECTIONS
    from services.egomotion import egomotion_config
    from services.gridcells.config import GridCellsConfig

    assert set(SECTIONS) == {"runtime", "run", *SERVICES}
    path = tmp_path / "typo.toml"
    path.write_text("[gridcells]\ndecoder = \"fft\"\n[sterio]\nransac_iterations = 3\n")
    with pytest.raises(ConfigError, match=r"unknown table \[sterio\]"):
        load_config(GridCellsConfig, "gridcells", config_file=path, environ={})
    with pytest.raises(ConfigError, match=r"unknown table \[sterio\]"):
        egomotion_config(config_file=path, environ={})
    path.write_text("[sterio]\nransac_iterations = 3\n")   # no [egomotion], no estimator: a whole file, mistyped
    with pytest.raises(ConfigError, match=r"unknown table \[sterio\]"):
        egomotion_config(config_file=path, environ={})



def test_the_choice_lists_name_what_the_cores_hold():
    from services.common import stages
    from services.egomotion import ESTIMATORS
    from services.gridcells.decoders import DECODERS

    assert tuple(ESTIMATORS) == stages.ESTIMATORS
    assert (*DECODERS, "calibrated") == stages.DECODERS
    from services.gridcells.config import DIRECTION_SIGMA
    assert tuple(DIRECTION_SIGMA) == stages.DECODERS


def test_the_process_settings_are_read_once_and_checked(tmp_path):
    from services.common.environment import VARIABLES, cache_folder, process_params

    assert set(VARIABLES) <= set(ENVIRONMENT.split())
    assert process_params({"GRIDSLAM_FFT": " SciPy "}).fft == "scipy"
    with pytest.raises(ConfigError, match="GRIDSLAM_FFT='fast': choose one of auto, fftw, scipy"):
        process_params({"GRIDSLAM_FFT": "fast"})
    assert cache_folder({"GRIDSLAM_CACHE": str(tmp_path)}) == tmp_path
    assert cache_folder({"XDG_CACHE_HOME": str(tmp_path)}) == tmp_path / "gridslam"
    assert cache_folder({}) == Path.home() / ".cache" / "gridslam"


def test_every_process_computes_with_one_blas_kernel(monkeypatch):
    from services.common import environment

    monkeypatch.setattr(environment.platform, "machine", lambda: "x86_64")
    environ: dict[str, str] = {}
    assert environment.pin_blas_kernel(environ, {"sse2", "avx2", "fma"})
    assert environ == {"OPENBLAS_CORETYPE": "Haswell"}
    mine = {"OPENBLAS_CORETYPE": "SkylakeX"}   # the user's own choice stays
    assert not environment.pin_blas_kernel(mine, {"avx2", "fma"}) and mine == {"OPENBLAS_CORETYPE": "SkylakeX"}
    environ = {}
    assert not environment.pin_blas_kernel(environ, {"sse2", "avx"}) and environ == {}   # no AVX2: never forced
    monkeypatch.setattr(environment.platform, "machine", lambda: "aarch64")
    assert not environment.pin_blas_kernel(environ, {"avx2", "fma"}) and environ == {}


def flag_actions(parser) -> dict[str, object]:
    """dest → argparse action of every flag of ``parser``."""
    return {action.dest: action for action in parser._actions if action.option_strings}


def sub_parser(*names):
    from services.cli import build_parser

    parser = build_parser()
    for name in names:
        parser = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction").choices[name]
    return parser


def test_the_run_settings_are_declared_once():
    """[run]'s own keys and `gridslam run`'s flags come from one declaration (RunParams): the
    same help, default and bounds; a key with no flag (window, stall_timeout) is config only."""
    from services.cli.run import RUN_DESTS
    from services.common.run_settings import RunOutputParams, RunParams
    from services.pipeline.runner import RunConfig

    actions = flag_actions(sub_parser("run"))
    flagless = set()
    for field in dataclasses.fields(RunParams):
        model_field = RunConfig.model_fields[field.name]
        assert model_field.description == field.metadata["help"], field.name
        default = model_field.get_default() if not model_field.is_required() else dataclasses.MISSING
        assert default == field.default, field.name
        for bound in ("ge", "gt", "le", "lt"):
            if field.metadata[bound] is not None:
                assert any(getattr(m, bound, None) == field.metadata[bound] for m in model_field.metadata), (field.name, bound)
        action = actions.get(RUN_DESTS.get(field.name, field.name))
        if action is None:
            flagless.add(field.name)
            continue
        assert action.help.startswith(field.metadata["help"].replace("%", "%%")), field.name
        assert action.default is None, field.name   # not given: [run], the environment or the default decide
    assert flagless == {"window", "stall_timeout"}
    for field in dataclasses.fields(RunOutputParams):   # command line only
        assert field.name not in RunConfig.model_fields and actions[field.name].help.startswith(field.metadata["help"])


def test_what_the_run_passes_on_is_declared_with_its_service():
    """[run]'s keys that a service reads (the source's fov and bag topics, the place recognition,
    a saved map) carry the service's description and bounds, with None for "the service's"."""
    from services.loopclosure.service import LoopClosureConfig
    from services.pipeline.runner import RunConfig
    from services.source.service import SourceConfig

    for service, name in ((SourceConfig, "fov"), (SourceConfig, "odom_topic"), (SourceConfig, "stereo_tolerance"),
                          (LoopClosureConfig, "place_recognition"), (LoopClosureConfig, "fleet"),
                          (LoopClosureConfig, "map"), (LoopClosureConfig, "localize")):
        declared, passed = service.model_fields[name], RunConfig.model_fields[name]
        assert passed.description.startswith(declared.description.rstrip(".")), name
    assert RunConfig.model_fields["fov"].default is None
    for bad in ({"fov": 180}, {"stereo_tolerance": 0}, {"place_recognition": "orb"}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            RunConfig(source="synthetic:0", **bad)


def test_the_runtime_and_service_flags_come_from_their_declarations():
    from services.cli.service import service_parser
    from services.common.runtime import RuntimeConfig
    from services.common.service import ServiceParams

    actions = flag_actions(service_parser("egomotion")[0])
    for name, field in RuntimeConfig.model_fields.items():
        assert actions[name].help.startswith(field.description.rstrip(".")), name
        assert actions[name].default is None, name
    assert actions["instance"].help.startswith(dataclasses.fields(ServiceParams)[0].metadata["help"])


def test_the_offline_commands_flags_come_from_their_declarations():
    """integrate, simulate and map: each flag's help and default are its declaration's, and a
    value outside the declared bounds is refused as it is parsed, naming the flag."""
    from services.cli.integrate import IntegrateParams, NetworkRunParams
    from services.cli.map import BuildParams, ExportParams, RouteParams, SweepParams
    from services.cli.simulate import SimulateParams
    from services.common.stages import GridStageParams

    commands = {("integrate",): (IntegrateParams, NetworkRunParams, GridStageParams),
                ("simulate",): (SimulateParams, NetworkRunParams),
                ("map", "build"): (BuildParams,), ("map", "sweep"): (SweepParams,),
                ("map", "route"): (RouteParams,), ("map", "export"): (ExportParams,)}
    for names, declarations in commands.items():
        actions = flag_actions(sub_parser(*names))
        for params in declarations:
            for field in dataclasses.fields(params):
                if params is GridStageParams and field.name == "integrator":
                    continue   # integrate runs the grid (and dead reckoning beside it)
                if params is BuildParams and names == ("map", "sweep") and field.name in ("out", "title"):
                    continue   # build's only
                action = actions[field.name]
                assert action.help.startswith(field.metadata["help"].replace("%", "%%").rstrip(".")), (names, field.name)
                if field.default is not dataclasses.MISSING:
                    assert action.default == field.default, (names, field.name)
    from services.cli import build_parser

    for argv in (["integrate", "m.csv", "--noise-trans", "-0.1"], ["simulate", "--n-frames", "0"],
                 ["map", "build", "--images", "x", "--odometry", "o.csv", "--out", "d", "--same-place-radius", "0"]):
        with pytest.raises(SystemExit):
            build_parser().parse_args(argv)
