"""The node's health as diagnostic_msgs: one DiagnosticStatus, on ~/status and on /diagnostics.

/diagnostics is where `diagnostic_aggregator` and rqt_robot_monitor look; they group statuses by `name`, so the
name stays the same for the node's whole life ("<node name>: ESLAM") and `hardware_id` names the device
(`diagnostics.hardware_id`). The level says what needs attention, most important first:

    ERROR  the SLAM runtime crashed
    WARN   no input for `no_input_timeout` s (rgb-depth pairs, or odometry with odom_source topic), input rate below
           `min_input_rate`, still waiting for the first input or starting, inputs skipped, odometry gaps / jumps
           or missing odometry in the last period
    OK     tracking (or inactive: a lifecycle node deactivated on purpose)

`status_level` is pure, so the policy is tested without a node.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from visualization_msgs.msg import Marker

from eslam_core.runtime.api import RateMeter

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
# The input rate is measured over this window (seconds): long enough to be steady, short enough to see a stall.
INPUT_RATE_WINDOW_S = 5.0


class InputMonitor:
    """When each input last arrived, and the rate of rgb-depth pairs."""

    def __init__(self, now: Optional[float] = None) -> None:
        self.started = time.monotonic() if now is None else now
        self.last: dict[str, float] = {}
        self.pairs = RateMeter(INPUT_RATE_WINDOW_S)

    def arrived(self, name: str, now: Optional[float] = None) -> None:
        self.last[name] = time.monotonic() if now is None else now
        if name == "pair":
            self.pairs.tick(self.last[name])

    def silent_for(self, name: str, now: Optional[float] = None) -> float:
        """Seconds since `name` last arrived (since the monitor started, if never)."""
        now = time.monotonic() if now is None else now
        return now - self.last.get(name, self.started)

    def rate(self, now: Optional[float] = None) -> float:
        return self.pairs.rate(now)


@dataclass
class StatusInputs:
    """What the level depends on, gathered by the node each period."""

    failed: Optional[str] = None
    state: str = "running"  # waiting | starting | running | inactive | failed
    poses: int = 0
    silent_s: dict[str, float] = field(default_factory=dict)  # per watched input: seconds since it last arrived
    pair_rate_hz: float = 0.0
    measured_for_s: float = 0.0  # how long the rate has been measured (no rate warning before a full window)
    skipped_now: int = 0
    odometry_problems_now: dict[str, int] = field(default_factory=dict)  # {"odom_missing": 2, ...} this period
    lost: Optional[str] = None  # the camera is lost: why (the newest frame's tracking quality)
    degraded: Optional[str] = None  # the newest pose is degraded: why (its free direction and sigma)


def status_level(inputs: StatusInputs, no_input_timeout: float, min_input_rate: float) -> tuple[bytes, str]:
    """(level, message) of the node's DiagnosticStatus."""
    if inputs.failed:
        return ERROR, inputs.failed
    if inputs.state == "inactive":
        return OK, "inactive (deactivated): not tracking, the map is kept"
    silent = [name for name, seconds in inputs.silent_s.items() if no_input_timeout and seconds >= no_input_timeout]
    if silent:
        longest = max(inputs.silent_s[name] for name in silent)
        return WARN, (f"no input for {longest:.0f} s on {', '.join(silent)}: check that the topics are published "
                      f"and remapped")
    if inputs.state == "waiting":
        return WARN, "waiting for the first rgb + depth + camera info"
    if inputs.state == "starting":
        return WARN, "starting the SLAM runtime"
    if inputs.lost:
        return WARN, f"tracking lost ({inputs.lost}): no pose published, relocalizing against the keyframes"
    if inputs.degraded:
        return WARN, f"tracking degraded ({inputs.degraded}): poses published with that covariance, not mapped"
    if min_input_rate and inputs.measured_for_s >= INPUT_RATE_WINDOW_S and inputs.pair_rate_hz < min_input_rate:
        return WARN, f"input rate {inputs.pair_rate_hz:.1f} Hz is below {min_input_rate:g} Hz"
    if inputs.skipped_now:
        return WARN, f"{inputs.skipped_now} input(s) skipped in the last period"
    problems = {k: v for k, v in inputs.odometry_problems_now.items() if v}
    if problems:
        return WARN, "odometry: " + ", ".join(f"{v} {k.removeprefix('odom_')}" for k, v in problems.items()) + \
            " in the last period"
    return OK, f"tracking, {inputs.poses} poses published"


def diagnostic_array(name: str, hardware_id: str, level: bytes, message: str, values: dict[str, Any],
                     stamp: Any) -> DiagnosticArray:
    status = DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id)
    status.values = [KeyValue(key=key, value=diagnostic_value(value)) for key, value in values.items()]
    msg = DiagnosticArray(status=[status])
    msg.header.stamp = stamp
    return msg


# Text colour per level (RGBA): green, amber, red.
LEVEL_COLORS = {OK: (0.3, 1.0, 0.3, 1.0), WARN: (1.0, 0.75, 0.1, 1.0), ERROR: (1.0, 0.2, 0.2, 1.0)}


def status_marker(name: str, level: bytes, message: str, position: np.ndarray, frame_id: str,
                  stamp: Any) -> Marker:
    """The status as RViz text (RViz has no diagnostics display), floating at `position` (map coordinates)."""
    marker = Marker(ns="eslam_status", id=0, type=Marker.TEXT_VIEW_FACING, action=Marker.ADD, text=f"{name}: {message}")
    marker.header.frame_id, marker.header.stamp = frame_id, stamp
    marker.pose.position.x, marker.pose.position.y, marker.pose.position.z = (float(v) for v in position)
    marker.pose.orientation.w = 1.0
    marker.scale.z = 0.12  # text height, metres
    marker.color.r, marker.color.g, marker.color.b, marker.color.a = LEVEL_COLORS.get(level, LEVEL_COLORS[WARN])
    return marker


def diagnostic_value(value: Any) -> str:
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.6g}"
    return str(value)
