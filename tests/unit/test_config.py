"""Config precedence (defaults < preset < file < environment < flags) and one-line errors."""

import argparse

import pytest
from pydantic import BaseModel, ConfigDict, Field

from services.common.config import load_config
from services.common.errors import ConfigError
from services.common.runtime import RuntimeConfig, add_runtime_flags, runtime_from_args, zenoh_config


class Example(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")
    rate: float = Field(1.0, description="a rate")
    names: list[str] = Field(default_factory=list, description="some names")


def test_precedence(tmp_path):
    path = tmp_path / "gridslam.toml"
    path.write_text('[example]\nrate = 2.0\nnames = ["a"]\n')
    assert load_config(Example, "example").rate == 1.0
    assert load_config(Example, "example", config_file=path).rate == 2.0
    env = {"GRIDSLAM_EXAMPLE_RATE": "3.5", "GRIDSLAM_EXAMPLE_NAMES": "x, y"}
    from_env = load_config(Example, "example", config_file=path, environ=env)
    assert (from_env.rate, from_env.names) == (3.5, ["x", "y"])
    assert load_config(Example, "example", config_file=path, environ=env, overrides={"rate": 9, "names": None}).rate == 9


def test_wrong_type_names_the_section_field_and_file(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text('[example]\nrate = "fast"\n')
    with pytest.raises(ConfigError, match=r"\[example\] rate: .*" + str(path)):
        load_config(Example, "example", config_file=path)


def test_unknown_field_and_bad_toml_and_missing_file(tmp_path):
    unknown = tmp_path / "unknown.toml"
    unknown.write_text("[example]\nspeed = 1\n")
    with pytest.raises(ConfigError, match=r"\[example\] speed: Extra inputs"):
        load_config(Example, "example", config_file=unknown)
    broken = tmp_path / "broken.toml"
    broken.write_text("[example\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(Example, "example", config_file=broken)
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(Example, "example", config_file=tmp_path / "absent.toml")


def test_unknown_preset_lists_the_available_ones():
    with pytest.raises(ConfigError, match="unknown preset 'nowhere' for gridcells"):
        load_config(Example, "gridcells", preset="nowhere")


def parse(argv):
    parser = argparse.ArgumentParser()
    add_runtime_flags(parser)
    return parser.parse_args(argv)


def test_runtime_flags_override_environment(monkeypatch):
    monkeypatch.setenv("GRIDSLAM_RUNTIME_CONNECT", "tcp/10.0.0.1:7447,tcp/10.0.0.2:7447")
    monkeypatch.setenv("GRIDSLAM_RUNTIME_ROBOT", "envbot")
    runtime = runtime_from_args(parse(["--robot", "flagbot"]))
    assert runtime.connect == ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"]
    assert runtime.robot == "flagbot"
    assert runtime_from_args(parse(["-e", "tcp/127.0.0.1:9000"])).connect == ["tcp/127.0.0.1:9000"]


def test_router_defaults_and_bad_values():
    runtime = runtime_from_args(parse([]), mode="router", listen=["tcp/127.0.0.1:7447"], connect=[])
    assert (runtime.mode, runtime.listen, runtime.connect, runtime.multicast_scouting) == (
        "router", ["tcp/127.0.0.1:7447"], [], False)
    with pytest.raises(ConfigError, match=r"\[runtime\] robot"):
        runtime_from_args(parse(["--robot", "a/b"]))
    with pytest.raises(ConfigError, match="expected KEY:VALUE"):
        runtime_from_args(parse(["--cfg", "novalue"]))
    with pytest.raises(ConfigError, match="invalid Zenoh configuration"):
        zenoh_config(RuntimeConfig(cfg={"transport/link/tx/lease": "not-a-number"}))


def test_the_runs_ros2_graph_settings_are_graphparams_declared_once(tmp_path):
    """`gridslam run` passes --ros-domain-id, --ros-namespace, --ros-distro and --ros2-keys on to
    the ros2 service and a ros2: source; RunConfig derives them from GraphParams, None meaning
    the service's own default, and the bounds and choices are GraphParams'."""
    import dataclasses

    from services.pipeline.runner import RunConfig, graph_args
    from services.ros2wire.rmw_zenoh import DISTROS, KEY_STYLES, GraphParams

    names = [f.name for f in dataclasses.fields(GraphParams)]
    for f in dataclasses.fields(GraphParams):   # derived: GraphParams' help, its default named
        assert RunConfig.model_fields[f.name].description == f"{f.metadata['help']} (default: the service's, {f.default})"
    run = RunConfig(source="synthetic:0")
    assert [getattr(run, name) for name in names] == [None] * len(names)
    assert graph_args(run) == []   # nothing given: the services keep their defaults
    given = RunConfig(source="synthetic:0", ros_domain_id=7, ros_namespace="/bot", ros_distro="humble", ros2_keys="bridge")
    assert graph_args(given) == ["--ros-domain-id", "7", "--ros-namespace", "/bot", "--ros-distro", "humble",
                                 "--ros2-keys", "bridge"]
    for bad in ({"ros_domain_id": 233}, {"ros_distro": "foxy"}, {"ros2_keys": "dds"}):
        with pytest.raises(ValueError):
            RunConfig(source="synthetic:0", **bad)
    for distro in DISTROS:
        assert RunConfig(source="synthetic:0", ros_distro=distro).ros_distro == distro
    for keys in KEY_STYLES:
        assert RunConfig(source="synthetic:0", ros2_keys=keys).ros2_keys == keys
    # A [run] table of a config file fills them like any other run setting.
    path = tmp_path / "gridslam.toml"
    path.write_text('[run]\nsource = "synthetic:0"\nros_domain_id = 5\nros_distro = "kilted"\n')
    loaded = load_config(RunConfig, "run", config_file=path)
    assert (loaded.ros_domain_id, loaded.ros_distro, loaded.ros_namespace) == (5, "kilted", None)
