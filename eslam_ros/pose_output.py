"""The node's pose outputs: ~/pose, ~/odom, TF (map -> camera, or map -> odom in REP 105 mode), ~/map_to_odom and
~/path, from the runtime's pose updates and trajectory.

Every frame goes to the runtime with a `FrameTag` (the rgb image's stamp and frame, its arrival time, the robot
odometry at the frame), and the frame's pose update brings it back (PoseUpdate.tag), so that every output is stamped
with the stamp of the image it was computed from.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Odometry, Path as PathMsg

from eslam_core.tracking.information import PoseCovariance, covariance_at
from eslam_core.tracking.quality import degenerate_view
from eslam_ros.conversions import InvalidPoseError, path_cdr
from eslam_ros.node_params import NodeSettings
from eslam_ros.node_threads import LogThrottle
from eslam_ros.pose_messages import odometry, pose_stamped, twist_between
from eslam_ros.qos import output_qos
from eslam_ros.robot_odometry import FrameOdometry, RobotOdometry
from eslam_ros.tf_chain import TfOutput, TfSetup, base_in_map, map_to_odom, transform_stamped


@dataclass(frozen=True)
class FrameTag:
    """What the node keeps of a frame handed to the runtime, until its pose comes back."""

    stamp: Any  # builtin_interfaces/Time of the rgb image
    frame_id: str  # the rgb image's frame (the camera's optical frame)
    received: float  # time.monotonic() when the frame's images were complete
    odometry: Optional[FrameOdometry] = None  # REP 105 mode: the robot's odometry at the frame


@dataclass
class Latency:
    """Seconds from the arrival of a frame's images at the node to the publication of its pose."""

    count: int = 0
    total: float = 0.0
    last: float = float("nan")
    worst: float = 0.0

    def add(self, seconds: float) -> None:
        self.count += 1
        self.total += seconds
        self.last = seconds
        self.worst = max(self.worst, seconds)

    @property
    def mean(self) -> float:
        return self.total / self.count if self.count else float("nan")


@dataclass
class PoseCounts:
    """What was published (for ~/status)."""

    poses: int = 0
    paths: int = 0
    poses_invalid: int = 0  # poses that were not rigid transforms (NaN, not a rotation): not published, counted
    poses_lost: int = 0  # frames tracked while lost: ~/odom only, with an unknown covariance
    latency: Latency = field(default_factory=Latency)
    seconds: float = 0.0  # the node's own share of the work: poll, messages, TF


class PoseOutput:
    def __init__(self, node: Any, settings: NodeSettings, tf_setup: TfSetup, robot: Optional[RobotOdometry],
                 throttle: LogThrottle) -> None:
        self.node, self.settings, self.tf_setup, self.robot, self.throttle = node, settings, tf_setup, robot, throttle
        self.pose_pub = node.create_publisher(PoseStamped, "~/pose", output_qos())
        self.odom_pub = node.create_publisher(Odometry, "~/odom", output_qos())
        self.path_pub = node.create_publisher(PathMsg, "~/path", output_qos(1))
        self.tf_output = TfOutput(node, tf_setup.tf_output)
        self.map_to_odom_pub = (node.create_publisher(TransformStamped, "~/map_to_odom", output_qos())
                                if tf_setup.rep105 else None)
        self.counts = PoseCounts()
        self._previous: Optional[tuple[np.ndarray, float]] = None
        self.lost = False  # the newest pose update said the camera is lost
        self.degraded: Optional[str] = None  # the newest pose update was degraded: its free direction
        self.last_position = np.zeros(3)  # of the camera in map_frame, where the status text floats

    @property
    def publishers(self) -> list:
        return [p for p in (self.pose_pub, self.odom_pub, self.path_pub, self.map_to_odom_pub) if p is not None]

    def reset(self) -> None:
        """A new map: no twist from the old map's last pose."""
        self._previous = None

    def publish(self, updates) -> None:
        start = time.monotonic()
        for update in updates:
            self._publish(update)
        self.counts.seconds += time.monotonic() - start

    def _publish(self, update: Any) -> None:
        tag: Optional[FrameTag] = update.tag
        previous, self._previous = self._previous, (update.pose, update.timestamp)
        if tag is None:  # not a frame of the node's
            return
        stamp, map_frame = tag.stamp, self.settings.map_frame
        output = self.in_output_frame(update.pose, tag.frame_id)
        if output is None:
            return
        output_pose, child = output
        twist = (np.zeros(3), np.zeros(3))
        if previous:
            previous_output = self.in_output_frame(previous[0], tag.frame_id)
            twist = twist_between(previous_output[0], previous[1], output_pose, update.timestamp)
        try:
            covariance = None if update.covariance is None else covariance_at(
                update.covariance, output_pose[:3, 3] - update.pose[:3, 3])  # (the base's, with pose_frame base)
            pose, odom = pose_stamped(output_pose, stamp, map_frame), odometry(
                output_pose, twist, stamp, map_frame, child, update.quality, update.lost, covariance)
            tf = self._tf_of(update.pose, tag.odometry, stamp, child)
        except InvalidPoseError as error:  # NaN or not a rotation at all (drift is re-orthonormalised): skip it
            self.counts.poses_invalid += 1
            if self.throttle.allow("invalid_pose"):
                self.node.get_logger().warning(
                    f"pose of frame {update.index} not published: {error} [{self.counts.poses_invalid} invalid "
                    f"poses skipped, {self.counts.poses} published so far; publishing goes on]")
            return
        self.lost = update.lost
        self.degraded = degenerate_view(PoseCovariance(update.covariance)) if update.degraded and \
            update.covariance is not None else None
        if update.lost:  # no pose to act on: ~/odom says so with its covariance, ~/pose and TF wait
            self.odom_pub.publish(odom)
            self.counts.poses_lost += 1
            return
        self.pose_pub.publish(pose)
        self.odom_pub.publish(odom)
        self.last_position = update.pose[:3, 3].copy()
        if tf is not None:
            self.tf_output.send(tf)
            if self.map_to_odom_pub is not None:
                self.map_to_odom_pub.publish(tf)
        self.counts.poses += 1
        self.counts.latency.add(time.monotonic() - tag.received)

    def in_output_frame(self, camera_pose: np.ndarray, frame_id: str) -> Optional[tuple[np.ndarray, str]]:
        """(pose, child frame) of ~/pose, ~/odom and ~/path: the camera's, or the base's with pose_frame base (None
        while the extrinsic is unknown)."""
        s = self.settings
        if s.pose_frame == "camera":
            return camera_pose, s.tf_child_frame or frame_id
        base_camera = self.robot.base_camera(frame_id)
        if base_camera is None:
            if self.throttle.allow("no_extrinsic"):
                self.node.get_logger().warning(f"pose not published: no TF {s.base_frame} -> {frame_id} yet "
                                               f"(pose_frame base needs the camera extrinsic)")
            return None
        return base_in_map(camera_pose, base_camera), s.base_frame

    def _tf_of(self, camera_pose: np.ndarray, frame_odometry: Optional[FrameOdometry], stamp: Any,
               child: str) -> Optional[TransformStamped]:
        """The frame's transform: map -> odom (REP 105 mode, frames with odometry) or map -> camera."""
        s = self.settings
        if not self.tf_setup.rep105:
            return (transform_stamped(camera_pose, stamp, s.map_frame, child) if self.tf_setup.tf_output != "none"
                    else None)
        if frame_odometry is None or frame_odometry.odom_camera is None:
            return None
        return transform_stamped(map_to_odom(camera_pose, frame_odometry.odom_camera), stamp, s.map_frame,
                                 s.odom_frame)

    def publish_path(self, runtime: Any, camera_frame: str) -> None:
        """~/path: the trajectory with mapping's refinements, at most `path_max_poses` of it."""
        timestamps, poses = runtime.trajectory(self.settings.path_max_poses)
        finite = np.isfinite(poses).all(axis=(1, 2)) if len(timestamps) else np.zeros(0, bool)
        if finite.any() and self.settings.pose_frame == "base":
            base_camera = self.robot.base_camera(camera_frame)
            if base_camera is None:
                return
            poses = poses.copy()
            poses[finite] = base_in_map(poses[finite], base_camera)
        if finite.any():
            self.path_pub.publish(path_cdr(timestamps[finite], poses[finite], self.settings.map_frame))
            self.counts.paths += 1
