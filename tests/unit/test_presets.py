"""World settings from a preset, the config file's [source], the environment and flags (in that
order of precedence), and preset files: a base preset plus per-service tables, each service
taking what applies to it."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from services.cli.service import service_parser
from services.common.config import describe_preset, load_config, preset_applies, preset_values, read_toml
from services.common.errors import ConfigError
from services.egomotion import egomotion_config
from services.pipeline.runner import RunConfig, log_preset, service_args, source_args, source_settings
from services.source.service import config_from_args
from services.source.spec import load_preset, open_source, parse_world_flags

SERVICES = Path(__file__).resolve().parents[2] / "services"


def source_config(argv: list[str], monkeypatch, environ: dict[str, str] | None = None):
    for key, value in (environ or {}).items():
        monkeypatch.setenv(key, value)
    parser, _ = service_parser("source")
    return config_from_args(parser.parse_args(argv))


def test_world_settings_precedence(tmp_path, monkeypatch):
    config_file = tmp_path / "gridslam.toml"
    config_file.write_text('[source]\nlaps = 3\nspeed = 0.2\nwander = 0.0\n')
    base = ["--source", "synthetic:0", "--preset", "synthetic"]
    assert load_preset("synthetic")[1]["laps"] == 2
    assert source_config(base, monkeypatch).world() == {}  # the preset's own
    from_file = source_config([*base, "--config", str(config_file)], monkeypatch)
    assert from_file.world() == {"laps": 3, "speed": 0.2, "wander": 0.0}
    from_env = source_config([*base, "--config", str(config_file)], monkeypatch, {"GRIDSLAM_SOURCE_LAPS": "4"})
    assert from_env.world()["laps"] == 4
    flags = [*base, "--config", str(config_file), "--laps", "5", "--world", "speed=0.25", "--world", "noise=0"]
    from_flags = source_config(flags, monkeypatch, {"GRIDSLAM_SOURCE_LAPS": "4"})
    assert from_flags.world() == {"laps": 5, "speed": 0.25, "wander": 0.0, "noise": 0.0}
    world = open_source(from_flags.source, preset=from_flags.preset, world=from_flags.world(), mono=True, stop=1)
    assert (world.config.laps, world.config.speed, world.config.wander, world.config.length) == (5, 0.25, 0.0, 12.0)


def test_world_flags_are_typed_and_checked():
    assert parse_world_flags(["layout=campus", "speed=0.3", "laps=2", "noise=1"], laps=4) == {
        "layout": "campus", "speed": 0.3, "laps": 4, "noise": 1.0}
    with pytest.raises(ConfigError, match=r"--world lapz=2: expected KEY=VALUE with KEY one of .*laps"):
        parse_world_flags(["lapz=2"])
    with pytest.raises(ConfigError, match=r"--world laps=two: laps must be int"):
        parse_world_flags(["laps=two"])
    with pytest.raises(ConfigError, match=r"--world speed: expected KEY=VALUE"):
        parse_world_flags(["speed"])


def test_world_settings_errors_name_the_key(tmp_path, monkeypatch):
    bad = tmp_path / "bad.toml"
    bad.write_text('[source]\nlaps = "many"\n')
    with pytest.raises(ConfigError, match=rf"\[source\] laps: .*{bad.name}"):
        source_config(["--source", "synthetic:0", "--config", str(bad)], monkeypatch)
    with pytest.raises(ConfigError, match="world key 'laps' applies to the synthetic world only"):
        open_source("kitti:/nowhere", world={"laps": 2})
    with pytest.raises(ConfigError, match="laps = 0 is out of range"):
        open_source("synthetic:0", world={"laps": 0})


def write_preset(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "mine.toml"
    path.write_text(text)
    return path


def test_a_preset_file_applies_to_the_services_whose_keys_it_holds(tmp_path):
    path = write_preset(tmp_path, 'base = "synthetic"\n[source]\nlaps = 4\n[loopclosure]\nmatch_threshold = 0.05\n'
                                  '[egomotion.stereo]\nbucket_size_px = 40\n')
    synthetic = {name: read_toml(SERVICES / name / "presets" / "synthetic.toml") for name in ("loopclosure", "gridcells", "expmap")}
    assert preset_values("loopclosure", path) == {**synthetic["loopclosure"], "match_threshold": 0.05}
    assert preset_values("gridcells", path) == synthetic["gridcells"]  # no table: the base's
    camera, settings = load_preset(path)
    assert settings["laps"] == 4 and settings["speed"] == 0.1 and camera.baseline == 0.12
    egomotion = egomotion_config(str(path), environ={})
    assert egomotion.estimator == "stereo"
    assert egomotion.stereo.model_dump(exclude_unset=True) == {"bucket_size_px": 40, "features_per_bucket": 4}  # one level deep
    from services.loopclosure.service import LoopClosureConfig

    assert load_config(LoopClosureConfig, "loopclosure", preset=str(path)).match_threshold == 0.05
    config = RunConfig(source="synthetic:0", preset=str(path))
    for name in ("egomotion", "gridcells", "loopclosure", "expmap"):
        args = service_args(config, name, tmp_path)
        assert args[args.index("--preset") + 1] == str(path)
    assert "--preset" not in service_args(config, "viewer", tmp_path)
    assert describe_preset(path, ["source", "egomotion", "gridcells", "loopclosure", "expmap"]) == (
        f"preset file {path}: source, egomotion, loopclosure take keys from it (over preset 'synthetic'); "
        "gridcells, expmap stay on preset 'synthetic'")


def test_a_preset_file_without_base_says_which_services_run_on_defaults(tmp_path, caplog):
    path = write_preset(tmp_path, "laps = 3\nspeed = 0.2\n")  # the older flat shape: source keys
    assert load_preset(path)[1] == {"laps": 3, "speed": 0.2}
    assert preset_applies("source", path) and not preset_applies("loopclosure", path)
    config = RunConfig(source="synthetic:0", preset=str(path))
    assert "--preset" not in service_args(config, "loopclosure", tmp_path)
    assert source_args(config, 0, "map/pose")[source_args(config, 0, "map/pose").index("--preset") + 1] == str(path)
    with caplog.at_level(logging.INFO, logger="services.pipeline.runner"):
        log_preset(config, ["source", "egomotion", "loopclosure"])
    assert [r.levelname for r in caplog.records] == ["WARNING"]
    assert caplog.records[0].getMessage() == (f"preset file {path}: source takes keys from it; "
                                              "egomotion, loopclosure run on defaults (no base)")


def test_bad_preset_files_are_one_line_naming_file_and_key(tmp_path):
    from services.loopclosure.service import LoopClosureConfig

    cases = [
        ('base = "atlantis"\n', r"mine.toml: base 'atlantis' is not a preset \(available: .*synthetic"),
        ('base = "synthetic"\n[looplosure]\nwidth = 3\n', r"mine.toml: unknown table \[looplosure\]"),
        ('laps = 2\n[source]\nspeed = 0.2\n', r"mine.toml: key 'laps' outside a table"),
    ]
    for text, message in cases:
        path = write_preset(tmp_path, text)
        with pytest.raises(ConfigError, match=message):
            preset_values("gridcells", path)
        with pytest.raises(ConfigError, match=message):
            log_preset(RunConfig(source="synthetic:0", preset=str(path)), ["source"])
    path = write_preset(tmp_path, 'base = "synthetic"\n[loopclosure]\nthreshold = 0.05\n')
    with pytest.raises(ConfigError, match=r"\[loopclosure\] threshold: Extra inputs are not permitted \(from preset file .*mine.toml\)"):
        load_config(LoopClosureConfig, "loopclosure", preset=str(path))
    path = write_preset(tmp_path, 'base = "synthetic"\n[source]\nlapz = 2\n')
    with pytest.raises(ConfigError, match=r"mine.toml: unknown key 'lapz'"):
        load_preset(path)
    with pytest.raises(ConfigError, match=r"absent.toml: preset file not found"):
        preset_values("source", tmp_path / "absent.toml")


def test_the_run_resolves_the_source_as_its_service_will(tmp_path):
    config_file = tmp_path / "gridslam.toml"
    config_file.write_text("[source]\nlaps = 3\n")
    config = RunConfig(source="synthetic:0", preset="synthetic", config_file=config_file, world={"speed": 0.2, "wander": 0.0})
    assert source_settings(config).world() == {"laps": 3, "speed": 0.2, "wander": 0.0}
    args = source_args(config, 0, "map/pose")
    assert [args[i + 1] for i, a in enumerate(args) if a == "--world"] == ["speed=0.2", "wander=0.0"]
    parser, _ = service_parser("source")
    assert config_from_args(parser.parse_args(args[2:])).world() == {"laps": 3, "speed": 0.2, "wander": 0.0}


def test_sharded_runs_keep_a_fixed_window_of_whole_blocks():
    alone = source_args(RunConfig(source="synthetic:0", egomotion="stereo"), 0, "map/pose")
    sharded = source_args(RunConfig(source="synthetic:0", egomotion="stereo", egomotion_instances=2), 0, "map/pose")
    assert "--no-adaptive-window" not in alone and alone[alone.index("--window") + 1] == "8"
    assert "--no-adaptive-window" in sharded and int(sharded[sharded.index("--window") + 1]) >= 3 * 4


def test_the_run_and_its_egomotion_instances_resolve_one_block_size(tmp_path, monkeypatch):
    """The frames the runner keeps in flight follow the block size its egomotion children will
    use: the preset's estimator (kitti's is mono: 16), the config file, the environment; one
    instance runs frame after frame (no blocks, the plain window)."""
    from services.egomotion import resolve_sharding
    from services.egomotion.service import estimator_settings
    from services.pipeline.runner import service_args, shard_block

    def window(config):
        args = source_args(config, 0, "map/pose")
        return int(args[args.index("--window") + 1])

    def child_block(config):   # what the egomotion child resolves from the arguments it is given
        args = service_parser("egomotion")[0].parse_args(service_args(config, "egomotion", tmp_path)[2:])
        name, _ = estimator_settings(args)   # kitti's preset names mono
        return resolve_sharding(name, args.instances, args.shard_block, args.config)[1]

    monkeypatch.delenv("GRIDSLAM_EGOMOTION_SHARD_BLOCK", raising=False)
    kitti = RunConfig(source="synthetic:0", preset="kitti", egomotion_instances=2)
    assert shard_block(kitti) == child_block(kitti) == 16 and window(kitti) == 3 * 16
    alone = RunConfig(source="synthetic:0", preset="kitti")
    assert shard_block(alone) is None and child_block(alone) is None and window(alone) == 8
    config_file = tmp_path / "gridslam.toml"
    config_file.write_text("[egomotion]\nshard_block = 6\n")
    filed = kitti.model_copy(update={"config_file": config_file})
    assert shard_block(filed) == child_block(filed) == 6 and window(filed) == 3 * 6
    monkeypatch.setenv("GRIDSLAM_EGOMOTION_SHARD_BLOCK", "5")
    assert shard_block(filed) == child_block(filed) == 5 and window(filed) == 3 * 5
    assert window(alone) == 8
    # A deployment's GRIDSLAM_EGOMOTION_INSTANCES does not reach a run's children: the runner says how many.
    monkeypatch.setenv("GRIDSLAM_EGOMOTION_INSTANCES", "3")
    assert child_block(alone) is None
