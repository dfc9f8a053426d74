"""Quality of service of the node's and the bag player's topics, and the Fast DDS transport profile.

Matching rules that drive the choices (a subscription receives only from publishers it is compatible with):
- a best-effort subscription matches reliable and best-effort publishers; a reliable one only reliable publishers.
  So `sensor_data` (best effort) is the input default: it works with every camera driver.
- a transient-local subscription needs a transient-local publisher; a volatile one matches both. The mesh is
  published transient-local so that a viewer started late (rviz) still gets the last map.
"""
from __future__ import annotations

import os
from importlib import resources
from pathlib import Path
from typing import MutableMapping, Optional

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)

from eslam_ros.node_params import QOS_CHOICES


class QosChoiceError(ValueError):
    """An unknown QoS name was asked for."""


def input_qos(name: str, depth: int) -> QoSProfile:
    """QoS of the image and camera-info subscriptions: 'sensor_data' (best effort) or 'reliable'."""
    if name not in QOS_CHOICES:
        raise QosChoiceError(f"unknown input QoS '{name}': choose one of {', '.join(QOS_CHOICES)}")
    reliability = ReliabilityPolicy.BEST_EFFORT if name == "sensor_data" else ReliabilityPolicy.RELIABLE
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=reliability,
                      durability=DurabilityPolicy.VOLATILE)


def output_qos(depth: int = 10) -> QoSProfile:
    """Poses, odometry, path and status: reliable, volatile."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def latched_qos() -> QoSProfile:
    """The mesh: reliable and transient local, keeping the last message for subscribers that join later."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def player_qos(name: str, depth: int) -> QoSProfile:
    """QoS of the bag player's publishers: 'reliable' (matches every subscription; the default) or 'sensor_data'."""
    if name not in QOS_CHOICES:
        raise QosChoiceError(f"unknown player QoS '{name}': choose one of {', '.join(QOS_CHOICES)}")
    return input_qos(name, depth)


# ------------------------------------------------------------------------------------------------ transport

# Fast DDS reads its XML profile from this environment variable when a participant is created (before rclpy.init).
FASTDDS_PROFILE_VARIABLE = "FASTRTPS_DEFAULT_PROFILES_FILE"
# Set to 0 to keep Fast DDS's default transports in the node and the bag player.
SHM_OPT_OUT_VARIABLE = "ESLAM_SHM_PROFILE"
SHM_PROFILE_NAME = "fastdds_shm.xml"


class TransportProfileError(ValueError):
    """The shipped Fast DDS profile cannot be found."""


def shipped_fastdds_profile() -> Path:
    """Path of config/fastdds_shm.xml: in the source tree, or installed with the package (pip or colcon)."""
    in_tree = Path(__file__).resolve().parent.parent / "config" / SHM_PROFILE_NAME
    if in_tree.is_file():
        return in_tree
    packaged = resources.files("eslam_core") / "presets" / SHM_PROFILE_NAME
    if packaged.is_file():
        return Path(str(packaged))
    raise TransportProfileError(
        f"{SHM_PROFILE_NAME} is neither in {in_tree.parent} nor installed in eslam_core/presets; reinstall the "
        f"package (pip install . or colcon build), or set {SHM_OPT_OUT_VARIABLE}=0 to use Fast DDS's defaults"
    )


def use_shipped_fastdds_profile(environ: MutableMapping[str, str] = os.environ) -> Optional[Path]:
    """Point Fast DDS at the large-segment shared-memory profile, unless the user chose a profile or opted out.

    The shared-memory segment belongs to the publishing participant, so every process that publishes large
    messages (camera driver, bag player, the node's mesh) needs it. Returns the profile used, or None.
    Must run before rclpy.init().
    """
    if environ.get(SHM_OPT_OUT_VARIABLE, "1") == "0":
        return None
    if environ.get(FASTDDS_PROFILE_VARIABLE):
        return Path(environ[FASTDDS_PROFILE_VARIABLE])
    profile = shipped_fastdds_profile()
    environ[FASTDDS_PROFILE_VARIABLE] = str(profile)
    return profile
