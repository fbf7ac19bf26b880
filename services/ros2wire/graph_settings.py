"""The node's place in the ROS 2 graph as the services read it: GraphParams's flags
(--ros-domain-id, --ros-namespace, --ros-distro, --ros2-keys), the environment's ROS_DOMAIN_ID
and the `[ros2]` table. The ros2 service, `gridslam run --ros2` and the `ros2:` source read them
the same way (the settings themselves are declared once, in rmw_zenoh.GraphParams)."""

from __future__ import annotations

import argparse
import dataclasses
import os

from pydantic import ConfigDict, create_model

from services.common.config import load_config
from services.common.errors import ConfigError
from services.common.settings import add_flag, config_fields, params_of
from services.ros2wire.rmw_zenoh import GraphParams, WireError, normalise_namespace

# The graph's keys of [ros2] (GRIDSLAM_ROS2_*), for a reader of the graph alone (the ros2:
# source); the table's other keys are the ros2 service's, which checks them.
GraphConfig = create_model("GraphConfig", __config__=ConfigDict(frozen=True, extra="ignore"), **config_fields(GraphParams))


def graph_params(config) -> GraphParams:
    """The graph settings of a config, the namespace checked (ConfigError naming it)."""
    params = params_of(GraphParams, config)
    try:
        normalise_namespace(params.ros_namespace)
    except WireError as error:
        raise ConfigError(f"[ros2] ros_namespace: {error}") from None
    return params


GRAPH_SETTINGS = tuple(f.name for f in dataclasses.fields(GraphParams))   # their names, for flags and configs


def add_graph_arguments(parser: argparse.ArgumentParser) -> None:
    """--ros-domain-id, --ros-namespace, --ros-distro, --ros2-keys (GraphParams), shared by the
    service, `gridslam run` and `demo`; defaults None ("not given")."""
    for name in GRAPH_SETTINGS:
        add_flag(parser, GraphParams, name)


def graph_flags(args) -> dict:
    return {name: getattr(args, name, None) for name in GRAPH_SETTINGS}


def environment_defaults(environ=None) -> dict:
    """ROS_DOMAIN_ID of the environment, as ROS 2 reads it (a bad value: ConfigError naming it)."""
    text = (os.environ if environ is None else environ).get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return {}
    if not text.isdigit():
        raise ConfigError(f"ROS_DOMAIN_ID={text!r} is not a domain id (0-232)")
    return {"ros_domain_id": int(text)}


def load_graph_config(model, args_or_flags: dict, config_file=None):
    return load_config(model, "ros2", defaults=environment_defaults(), config_file=config_file, overrides=args_or_flags)
