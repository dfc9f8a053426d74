"""The node's parameters on rclpy: declared on the node (so that `ros2 param list` shows them, with their
descriptions) and read back into `NodeSettings` and the ESLAM `Config` (node_params.py: what they are and how they
are checked)."""
from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import ParameterDescriptor

from eslam_core.config import Config
from eslam_ros.node_params import (ESLAM_PREFIX, NodeSettings, base_config, check_odometry_mode, config_from_parameters,
                                   config_parameters, node_parameter_defaults, settings_from_parameters,
                                   unknown_eslam_parameters, unknown_parameter_error)


def declare_node_parameters(node: Any) -> None:
    """The node settings (not the eslam.* ones, whose defaults depend on the preset); declared once, so a node
    configured again keeps them."""
    for name, (default, doc) in node_parameter_defaults().items():
        if not node.has_parameter(name):
            node.declare_parameter(name, default, ParameterDescriptor(description=doc, dynamic_typing=True))


def read_parameters(node: Any) -> tuple[NodeSettings, Config]:
    """Declare every node and ESLAM parameter and read them back; a bad one is a NodeParameterError or ConfigError
    that names it."""
    declare_node_parameters(node)
    settings = settings_from_parameters({name: node.get_parameter(name).value for name in node_parameter_defaults()})
    base = base_config(settings)
    # rclpy silently ignores overrides of undeclared parameters: catch misspelt eslam.* keys here.
    unknown = unknown_eslam_parameters(getattr(node, "_parameter_overrides", {}), base)
    if unknown:
        raise unknown_parameter_error(unknown[0], base)
    defaults = config_parameters(base)
    for name, default in defaults.items():
        if not node.has_parameter(name):
            # (types are checked by the config, not by rclpy)
            node.declare_parameter(name, default, ParameterDescriptor(
                description=f"ESLAM setting {name[len(ESLAM_PREFIX):]} (see eslam_core.config)", dynamic_typing=True))
    origin = f"config file {settings.config_file}" if settings.config_file else f"preset '{settings.preset}'"
    config = config_from_parameters({name: node.get_parameter(name).value for name in defaults},
                                    f"ROS parameters eslam.* over {origin}")
    check_odometry_mode(settings, config)
    return settings, config
