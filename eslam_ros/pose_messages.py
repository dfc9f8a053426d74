"""The node's pose outputs as messages: ~/pose (PoseStamped), ~/odom (Odometry: the pose, its covariance in REP 103
order, and the twist between two poses)."""
from __future__ import annotations

from typing import Any, Optional

import numpy as np
from geometry_msgs.msg import PoseStamped, Vector3
from nav_msgs.msg import Odometry
from scipy.spatial.transform import Rotation

from eslam_ros.conversions import pose_to_msg


def twist_between(pose_a: np.ndarray, t_a: float, pose_b: np.ndarray, t_b: float) -> tuple[np.ndarray, np.ndarray]:
    """(linear, angular) velocity of the camera moving from pose_a to pose_b, in the camera frame of pose_b.

    Finite differences: linear = R_b^T (t_b - t_a) / dt; angular = rotation vector of R_a^T R_b / dt. Zero when
    dt <= 0 (the first pose, or equal stamps).
    """
    dt = t_b - t_a
    if dt <= 0:
        return np.zeros(3), np.zeros(3)
    linear = pose_b[:3, :3].T @ (pose_b[:3, 3] - pose_a[:3, 3]) / dt
    angular = Rotation.from_matrix(pose_a[:3, :3].T @ pose_b[:3, :3]).as_rotvec() / dt
    return linear, angular


def pose_stamped(pose: np.ndarray, stamp: Any, frame_id: str) -> PoseStamped:
    msg = PoseStamped(pose=pose_to_msg(pose))
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    return msg


# Pose covariance of ~/odom (x y z roll pitch yaw) where the tracker measured none (a pose from the odometry alone, a
# tracker without normal equations): a well-tracked pose is good to about a centimetre and half a degree, divided by
# its tracking quality; a lost one is unknown.
TRACKED_SIGMA = (0.01, 0.01, 0.01, 0.01, 0.01, 0.01)
LOST_VARIANCE = 1e6


def pose_covariance(quality: float, lost: bool, measured: Optional[np.ndarray] = None) -> list[float]:
    """~/odom's 36 values: the tracker's covariance (6x6, already in the published pose's frame) where it measured
    one, else the stand-in above."""
    if lost:
        return [float(v) for v in np.diag([LOST_VARIANCE] * 6).reshape(-1)]
    if measured is not None:
        return [float(v) for v in np.asarray(measured, dtype=np.float64).reshape(-1)]
    variances = [(s / max(quality, 0.05)) ** 2 for s in TRACKED_SIGMA]
    return [float(v) for v in np.diag(variances).reshape(-1)]


def odometry(pose: np.ndarray, twist: tuple[np.ndarray, np.ndarray], stamp: Any, frame_id: str,
             child_frame_id: str, quality: float = 1.0, lost: bool = False,
             covariance: Optional[np.ndarray] = None) -> Odometry:
    msg = Odometry(child_frame_id=child_frame_id)
    msg.pose.covariance = pose_covariance(quality, lost, covariance)
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.pose.pose = pose_to_msg(pose)
    linear, angular = twist
    msg.twist.twist.linear = Vector3(x=float(linear[0]), y=float(linear[1]), z=float(linear[2]))
    msg.twist.twist.angular = Vector3(x=float(angular[0]), y=float(angular[1]), z=float(angular[2]))
    return msg
