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
from eslam_ros.qos import output_qos

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
    map_disagreement_cm: Optional[float] = None  # the map disagrees with itself by this much (else None)


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
    if inputs.map_disagreement_cm is not None:
        return WARN, (f"the map disagrees with itself: the newest keyframe lies {inputs.map_disagreement_cm:.0f} cm "
                      f"from where older keyframes place it (a slide mapped earlier); poses carry it in their "
                      f"covariance")
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


def health_values(node: Any) -> dict[str, Any]:
    """The runtime's health figures and a SLAM node's counters (slam_node.py), as published on ~/status."""
    values: dict[str, Any] = {"runtime": node.state(), "ready": node.ready(),
                              "tf_mode": node.tf_setup.describe(node.settings, node.camera_frame or "<image frame_id>"),
                              "tracking_mode": node.config.tracking.mode}
    if node.runtime is not None and not node.failed:
        values.update(node.runtime.health().as_dict())
    values["frames_accepted"] = node.pipeline.frames_accepted
    values["pairs"] = node.pipeline.pairs
    # (copied at once: the inputs' thread may add a key meanwhile)
    values.update(dict(node.pipeline.unpaired))
    skipped = dict(node.pipeline.skipped)
    values.update({f"skipped_{reason}": count for reason, count in skipped.items()})
    values["skipped_total"] = sum(skipped.values())
    poses = node.poses.counts
    values["poses_published"] = poses.poses
    values["poses_invalid"] = poses.poses_invalid
    values["poses_lost"] = poses.poses_lost
    values.update(node.mesh.status())
    values["stream_restarts"] = node.restarts
    values["frames_dropped_while_starting"] = node.host.dropped_while_starting
    held = node.host.held
    values["start_queue_frames"] = len(held)
    values["start_queue_bytes"] = held.bytes
    values["start_queue_peak_bytes"] = held.peak_bytes
    values["start_queue_budget_bytes"] = node.settings.start_queue_bytes
    values["input_rate_hz"] = node.inputs.rate()
    for name in node.watched_inputs():
        values[f"seconds_since_{name.replace('/', '_')}"] = node.inputs.silent_for(name)
    if node.odometry is not None:
        values.update(dict(node.odometry.counts))
        values["frames_waiting_for_odometry"] = len(node.odometry)
    values["latency_ms_receive_to_pose_last"] = 1000 * poses.latency.last
    values["latency_ms_receive_to_pose_mean"] = 1000 * poses.latency.mean
    values["latency_ms_receive_to_pose_max"] = 1000 * poses.latency.worst
    values["node_ms_per_pair_in"] = 1000 * node.input_seconds / max(node.pipeline.pairs, 1)
    values["node_ms_per_pose_out"] = 1000 * poses.seconds / max(poses.poses, 1)
    return values


class StatusReport:
    """~/status and /diagnostics (the same DiagnosticArray) and ~/status_marker (its summary above the camera), each
    status period: the node's health figures, with the level and summary of `status_level`. Keeps what the level
    compares with the last period (poses, skipped inputs, odometry problems)."""

    ODOMETRY_PROBLEMS = ("odom_missing", "odom_gaps", "odom_jumps", "odom_rejected")

    def __init__(self, node: Any, hardware_id: str, map_frame: str, up: np.ndarray, no_input_timeout: float,
                 min_input_rate: float) -> None:
        self.name = f"{node.get_name()}: ESLAM"  # the same for the node's whole life: aggregators group by it
        self.hardware_id, self.map_frame, self.up = hardware_id, map_frame, up
        self.no_input_timeout, self.min_input_rate = no_input_timeout, min_input_rate
        self.status_pub = node.create_publisher(DiagnosticArray, "~/status", output_qos())
        self.diagnostics_pub = node.create_publisher(DiagnosticArray, "/diagnostics", output_qos())
        self.marker_pub = node.create_publisher(Marker, "~/status_marker", output_qos(1))
        self._poses, self._skipped, self._problems = (0, time.monotonic()), 0, {}

    @property
    def publishers(self) -> list:
        return [self.status_pub, self.diagnostics_pub, self.marker_pub]

    def publish(self, values: dict[str, Any], inputs: StatusInputs, odometry: bool, position: np.ndarray,
                stamp: Any, now: Optional[float] = None) -> None:
        """`values`: the health figures; `inputs`: the level's inputs but the per-period counts, filled in here
        (odometry problems where the node takes `odometry`)."""
        now = time.monotonic() if now is None else now
        poses_before, since = self._poses
        values["pose_rate_hz"] = (inputs.poses - poses_before) / max(now - since, 1e-9)
        self._poses = (inputs.poses, now)
        inputs.skipped_now, self._skipped = values["skipped_total"] - self._skipped, values["skipped_total"]
        problems = {key: values.get(key, 0) for key in self.ODOMETRY_PROBLEMS}
        inputs.odometry_problems_now = {key: count - self._problems.get(key, 0) for key, count in problems.items()
                                        } if odometry else {}
        self._problems = problems
        level, summary = status_level(inputs, self.no_input_timeout, self.min_input_rate)
        msg = diagnostic_array(self.name, self.hardware_id, level, summary, values, stamp)
        self.status_pub.publish(msg)
        self.diagnostics_pub.publish(msg)
        self.marker_pub.publish(status_marker(self.name, level, summary, position + self.up, self.map_frame, stamp))
