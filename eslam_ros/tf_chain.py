"""The node's place in the robot's TF tree: what it publishes, and where odometry and extrinsic come from.

Two arrangements (docs/ros.md, "Robot integration"):

- *camera* (odom_frame and base_frame empty; the default): `map -> <camera optical frame>`. The camera frame must
  then have no other parent (or use `tf_child_frame`).
- *REP 105* (odom_frame and base_frame set): the robot already publishes `odom -> base_link` (its odometry) and
  `base_link -> ... -> camera` (the extrinsic); the node publishes only the correction `map -> odom`:

      T_map_odom = T_map_cam @ inv(T_odom_cam),   T_odom_cam = T_odom_base @ T_base_cam

  so that `map -> odom -> base -> camera` gives the SLAM pose of the camera and the tree stays a tree. The map frame
  is made to coincide with odom at the first frame (the first pose is seeded with T_odom_cam), so map has odom's
  axes (REP 103: x forward, y left, z up), not the optical axes of the first camera.

Where the odometry and the extrinsic come from depends on the installation:
- a ROS installation (tf2_ros imports): both from TF, odometry interpolated at the image stamp by tf2;
- the pip install (no tf2_ros, no tf2_msgs): the extrinsic is the `base_to_camera` parameter and the odometry a
  nav_msgs/Odometry topic; `map -> odom` goes on the `~/map_to_odom` topic (geometry_msgs/TransformStamped), and
  also on /tf when tf2_msgs was generated (see docs/ros.md).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional, Sequence

import numpy as np
from geometry_msgs.msg import TransformStamped, Vector3
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from eslam_core.geometry import quaternion_xyzw_to_matrix
from eslam_ros.conversions import pose_to_msg
from eslam_ros.node_params import NodeParameterError, NodeSettings
from eslam_ros.odometry import OdomLookup, OdomStatus

try:  # a real ROS installation
    import tf2_ros
except ImportError:
    tf2_ros = None
try:  # part of a ROS installation, or generated from its one-line .msg (docs/ros.md)
    from tf2_msgs.msg import TFMessage
except ImportError:
    TFMessage = None


# ================================================================================================= the math


def pose_from_xyz_quaternion(values: Sequence[float]) -> np.ndarray:
    """4x4 pose of [x, y, z, qx, qy, qz, qw] (the quaternion is normalised)."""
    pose = np.eye(4)
    pose[:3, :3] = quaternion_xyzw_to_matrix(np.asarray(values[3:], dtype=np.float64))
    pose[:3, 3] = values[:3]
    return pose


def camera_in_odom(odom_base: np.ndarray, base_camera: np.ndarray) -> np.ndarray:
    """T_odom_cam: the odometry of the base carried to the camera by the extrinsic."""
    return odom_base @ base_camera


def map_to_odom(map_camera: np.ndarray, odom_camera: np.ndarray) -> np.ndarray:
    """T_map_odom, the correction that makes map -> odom -> ... -> camera equal the SLAM pose of the camera."""
    return map_camera @ np.linalg.inv(odom_camera)


def base_in_map(map_camera: np.ndarray, base_camera: np.ndarray) -> np.ndarray:
    """T_map_base of the SLAM camera pose, for poses and paths given for the base."""
    return map_camera @ np.linalg.inv(base_camera)


def transform_stamped(pose: np.ndarray, stamp: Any, frame_id: str, child_frame_id: str) -> TransformStamped:
    p = pose_to_msg(pose)
    msg = TransformStamped(child_frame_id=child_frame_id)
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.transform.translation = Vector3(x=p.position.x, y=p.position.y, z=p.position.z)
    msg.transform.rotation = p.orientation
    return msg


def transform_to_pose(msg: Any) -> np.ndarray:
    """4x4 pose of a geometry_msgs/Transform."""
    t, q = msg.translation, msg.rotation
    return pose_from_xyz_quaternion([t.x, t.y, t.z, q.x, q.y, q.z, q.w])


# ================================================================================================= the setup


@dataclass(frozen=True)
class TfSetup:
    """What the node publishes on TF and where its odometry and extrinsic come from; said once in the log and in
    every status (`tf_mode`)."""

    rep105: bool
    odometry: str  # "none", "topic" or "tf"
    extrinsic: str  # "none", "parameter" or "tf"
    tf_output: str  # "tf2_ros", "tf2_msgs" (a plain /tf publisher) or "none"

    def describe(self, s: NodeSettings, camera: str = "<image frame_id>") -> str:
        tf = {"tf2_ros": "on /tf", "tf2_msgs": "on /tf (tf2_msgs publisher)",
              "none": "not on /tf (no tf2_ros / tf2_msgs)"}[self.tf_output]
        if not self.rep105:
            child = s.tf_child_frame or camera
            return f"camera mode: {s.map_frame} -> {child} {tf}; no odometry"
        odometry = "nav_msgs/Odometry on 'odom'" if self.odometry == "topic" else "TF"
        extrinsic = "the base_to_camera parameter" if self.extrinsic == "parameter" else "TF"
        return (f"REP 105 mode: {s.map_frame} -> {s.odom_frame} {tf} and on ~/map_to_odom; {s.odom_frame} -> "
                f"{s.base_frame} from {odometry}, {s.base_frame} -> camera from {extrinsic}")


def select_setup(s: NodeSettings, have_tf2_ros: bool = tf2_ros is not None,
                 have_tf2_msgs: bool = TFMessage is not None) -> TfSetup:
    """The arrangement the settings ask for on this installation; an impossible one is a NodeParameterError."""
    tf_output = "none"
    if s.publish_tf:
        tf_output = "tf2_ros" if have_tf2_ros else "tf2_msgs" if have_tf2_msgs else "none"
    if not s.rep105:
        return TfSetup(False, "none", "none", tf_output)
    odometry = s.odom_source if s.odom_source != "auto" else ("tf" if have_tf2_ros else "topic")
    if odometry == "tf" and not have_tf2_ros:
        raise NodeParameterError(
            "ROS parameter 'odom_source' = 'tf' needs tf2_ros, which is not installed (a pip install has no TF): "
            "use odom_source:=topic with the robot's nav_msgs/Odometry remapped to 'odom', or run on a ROS "
            "installation")
    extrinsic = "parameter" if s.base_to_camera else "tf" if have_tf2_ros else ""
    if not extrinsic:
        raise NodeParameterError(
            f"ROS parameter 'base_to_camera' is empty and tf2_ros is not installed: give the pose of the camera's "
            f"optical frame in '{s.base_frame}' as [x, y, z, qx, qy, qz, qw] (e.g. -p base_to_camera:=[0.1, 0.0, "
            f"0.3, -0.5, 0.5, -0.5, 0.5] for a camera 10 cm ahead and 30 cm above looking forward)")
    return TfSetup(True, odometry, extrinsic, tf_output)


# ================================================================================================= ROS side


def tf_qos() -> QoSProfile:
    """/tf as tf2_ros's TransformBroadcaster publishes it (DynamicBroadcasterQoS): reliable, volatile, depth 100."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


class TfOutput:
    """Sends transforms on /tf with tf2_ros, or with a plain tf2_msgs/TFMessage publisher where only tf2_msgs
    exists (the same topic, type and QoS)."""

    def __init__(self, node: Any, kind: str) -> None:
        self.kind = kind
        self._broadcaster = tf2_ros.TransformBroadcaster(node) if kind == "tf2_ros" else None
        self._publisher = node.create_publisher(TFMessage, "/tf", tf_qos()) if kind == "tf2_msgs" else None

    def send(self, transform: TransformStamped) -> None:
        if self._broadcaster is not None:
            self._broadcaster.sendTransform(transform)
        elif self._publisher is not None:
            self._publisher.publish(TFMessage(transforms=[transform]))


class TfOdometry:
    """odom -> base at image stamps and base -> camera, from a tf2 buffer (a ROS installation)."""

    def __init__(self, node: Any, odom_frame: str, base_frame: str) -> None:
        self.odom_frame, self.base_frame = odom_frame, base_frame
        self.buffer = tf2_ros.Buffer()
        self.listener = tf2_ros.TransformListener(self.buffer, node, spin_thread=False)

    def lookup(self, stamp: float) -> OdomLookup:
        from rclpy.time import Time

        try:
            msg = self.buffer.lookup_transform(self.odom_frame, self.base_frame,
                                               Time(nanoseconds=int(round(stamp * 1e9))))
        except tf2_ros.ExtrapolationException as error:  # "into the future": the odometry is not there yet
            status = OdomStatus.WAIT if "future" in str(error) else OdomStatus.MISSING
            return OdomLookup(status, message=f"TF {self.odom_frame} -> {self.base_frame}: {error}")
        except (tf2_ros.LookupException, tf2_ros.ConnectivityException) as error:
            return OdomLookup(OdomStatus.WAIT, message=f"TF {self.odom_frame} -> {self.base_frame}: {error}")
        return OdomLookup(OdomStatus.MATCHED, transform_to_pose(msg.transform))

    def extrinsic(self, camera_frame: str) -> Optional[np.ndarray]:
        """T_base_cam, the latest TF has (a rigid mount: its stamp does not matter); None while unknown."""
        from rclpy.time import Time

        try:
            msg = self.buffer.lookup_transform(self.base_frame, camera_frame, Time())
        except (tf2_ros.LookupException, tf2_ros.ConnectivityException, tf2_ros.ExtrapolationException):
            return None
        return transform_to_pose(msg.transform)
