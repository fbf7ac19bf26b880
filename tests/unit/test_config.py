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
