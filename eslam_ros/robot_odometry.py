"""The node's odometry input in REP 105 mode: each accepted frame gets the robot's odometry at its stamp.

    nav_msgs/Odometry on `odom` -> OdometryBuffer --+
                         or TF (tf2 buffer)  -------+-- lookup(stamp) -- OdometryWait (frames wait, in order)
                                                                 |
      odom -> base (raw) --- ContinuousOdometry (jumps taken out) --- @ base -> camera --- FrameOdometry

`FrameOdometry.odom_camera` (raw T_odom_cam) gives map -> odom once the frame's pose is known;
`FrameOdometry.slam_pose` (continuous T_odom_cam) is what SLAM gets as `Frame.odom_pose`. Every problem (a gap, a
jump, missing odometry, a message in the wrong frames) is counted in `counts` (shown in ~/status) and returned
with a message for the log.
"""
from __future__ import annotations

import dataclasses
import threading
from dataclasses import dataclass
from typing import Any, Callable, Generic, Iterator, Optional, TypeVar

import numpy as np

from eslam_core.camera import Frame

from eslam_ros.conversions import msg_to_pose, stamp_to_sec
from eslam_ros.node_params import NodeSettings
from eslam_ros.odometry import ContinuousOdometry, OdometryBuffer, OdometryWait, OdomStatus
from eslam_ros.tf_chain import TfOdometry, TfSetup, camera_in_odom, pose_from_xyz_quaternion

Item = TypeVar("Item")


@dataclass(frozen=True)
class FrameOdometry:
    """The odometry of one frame; the poses are None when there is none (then `problem` says why)."""

    odom_camera: Optional[np.ndarray] = None  # raw T_odom_cam at the stamp
    slam_pose: Optional[np.ndarray] = None  # continuous T_odom_cam: Frame.odom_pose
    base_camera: Optional[np.ndarray] = None  # T_base_cam
    problem: Optional[OdomStatus] = None
    message: str = ""
    jumped: bool = False


class RobotOdometry(Generic[Item]):
    def __init__(self, settings: NodeSettings, setup: TfSetup, tf_odometry: Optional[TfOdometry] = None) -> None:
        s = settings
        self.settings, self.setup = s, setup
        self.tf = tf_odometry
        self.buffer = OdometryBuffer(max_gap=s.odom_max_gap) if setup.odometry == "topic" else None
        if self.buffer is None and tf_odometry is None:
            raise ValueError("RobotOdometry needs an odometry topic buffer or a TF buffer")
        self.wait: OdometryWait[tuple[str, float, Item]] = OdometryWait(
            lambda stamp: (self.buffer or self.tf).lookup(stamp), s.odom_wait)
        self.continuity = ContinuousOdometry(s.odom_max_speed, s.odom_max_angular_speed)
        self._base_camera = pose_from_xyz_quaternion(s.base_to_camera) if s.base_to_camera else None
        self._tf_extrinsics: dict[str, np.ndarray] = {}
        # The node takes odometry messages on a callback group (a thread) of their own (see SlamNode.__init__).
        self._lock = threading.Lock()
        self.counts = {"odom_messages": 0, "odom_rejected": 0, "odom_matched": 0, "odom_missing": 0,
                       "odom_gaps": 0, "odom_jumps": 0, "odom_frames_skipped": 0}
        self.map_started = False  # a frame of this map had odometry: the map frame is seeded (frame_with_odometry)

    # ------------------------------------------------------------------------------------------------ inputs

    def add_message(self, msg: Any, now: float) -> Optional[str]:
        """A nav_msgs/Odometry message that arrived at `now`; returns a warning when it is refused (frames other than the configured)."""
        s = self.settings
        if msg.header.frame_id != s.odom_frame or msg.child_frame_id != s.base_frame:
            self.counts["odom_rejected"] += 1
            return (f"odometry message ignored: it is {msg.header.frame_id!r} -> {msg.child_frame_id!r} but "
                    f"odom_frame -> base_frame are {s.odom_frame!r} -> {s.base_frame!r}; set those parameters to the "
                    f"odometry's frames")
        with self._lock:
            self.counts["odom_messages"] += 1
            self.buffer.add(stamp_to_sec(msg.header.stamp), msg_to_pose(msg.pose.pose))
            self.wait.odometry_arrived(now)
        return None

    def push(self, stamp: float, frame_id: str, item: Item, now: float) -> None:
        with self._lock:
            self.wait.push(stamp, (frame_id, stamp, item), now)

    def __len__(self) -> int:
        return len(self.wait)

    # ------------------------------------------------------------------------------------------------ outputs

    def base_camera(self, frame_id: str) -> Optional[np.ndarray]:
        """T_base_cam of the camera frame `frame_id`: the parameter, or TF (kept once found: a rigid mount)."""
        if self._base_camera is not None:
            return self._base_camera
        if frame_id not in self._tf_extrinsics and self.tf is not None:
            found = self.tf.extrinsic(frame_id)
            if found is not None:
                self._tf_extrinsics[frame_id] = found
        return self._tf_extrinsics.get(frame_id)

    def release(self, now: float, flush: bool = False) -> list[tuple[Item, FrameOdometry]]:
        """The frames whose odometry is settled (known, or given up on), in arrival order."""
        out = []
        with self._lock:
            settled = self.wait.release(now, flush)
        for (frame_id, stamp, item), lookup in settled:
            base_camera = self.base_camera(frame_id)
            if lookup.status != OdomStatus.MATCHED:
                self.counts["odom_gaps" if lookup.status == OdomStatus.GAP else "odom_missing"] += 1
                out.append((item, FrameOdometry(base_camera=base_camera, problem=lookup.status,
                                                message=lookup.message)))
                continue
            if base_camera is None:
                self.counts["odom_missing"] += 1
                out.append((item, FrameOdometry(problem=OdomStatus.MISSING, message=(
                    f"no TF {self.settings.base_frame} -> {frame_id} (the camera extrinsic): publish it (robot_state_"
                    f"publisher / static_transform_publisher) or set base_to_camera"))))
                continue
            continuous, jumped = self.continuity.step(stamp, lookup.pose)
            self.counts["odom_matched"] += 1
            self.counts["odom_jumps"] += int(jumped)
            out.append((item, FrameOdometry(camera_in_odom(lookup.pose, base_camera),
                                            camera_in_odom(continuous, base_camera), base_camera, jumped=jumped,
                                            message="odometry jumped between two frames (faster than odom.max_speed"
                                                    " / odom.max_angular_speed): SLAM gets it without the jump, "
                                                    "map -> odom takes it up" if jumped else "")))
        return out

    def settled(self, now: float, flush: bool, external: bool,
                warn: Callable[[str, str], None]) -> Iterator[Item]:
        """The held frames (AcceptedFrames) whose odometry is settled, as SLAM gets them (`frame_with_odometry`),
        each carrying its odometry where it has one; frames that cannot go on are counted (odom_frames_skipped).
        `warn(kind, message)` for a frame without odometry or with a jump."""
        for accepted, odometry in self.release(now, flush):
            if odometry.problem is not None or odometry.jumped:
                warn(odometry.problem.value if odometry.problem is not None else "jump",
                     f"frame at {accepted.frame.timestamp:.3f}: {odometry.message}")
            frame = frame_with_odometry(accepted.frame, odometry, self.map_started, external)
            if frame is None:
                self.counts["odom_frames_skipped"] += 1
                continue
            self.map_started = self.map_started or odometry.problem is None
            yield dataclasses.replace(accepted, frame=frame, odometry=odometry if odometry.problem is None else None)

    def reset(self) -> None:
        """A new map: the odometry starts afresh (frames still waiting stay)."""
        self.continuity.reset()
        self.map_started = False


def frame_with_odometry(frame: Frame, odometry: FrameOdometry, map_started: bool, external: bool) -> Optional[Frame]:
    """The frame as SLAM gets it: with `odom_pose`, and, at the first frame of a map, `pose` seeded with it (so that
    map and odom coincide there and the map has odom's REP 103 axes). None when the frame cannot go on: a map starts
    only at a frame with odometry, and tracking.mode external needs odometry for every frame. Other frames without
    odometry are tracked with the constant-velocity prior."""
    if odometry.problem is not None:
        return frame if map_started and not external else None
    return dataclasses.replace(frame, odom_pose=odometry.slam_pose, pose=frame.pose if map_started else
                               odometry.slam_pose)
