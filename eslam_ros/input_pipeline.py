"""Messages in, frames out: rgb and depth images paired by approximate time, converted and checked against the
camera (`InputPipeline`). Holds no ROS node: the live node (`slam_node.py`) and the offline bag runner (`bag.py`)
share it."""
from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass
from enum import Enum
from typing import Any, Optional, Union

from eslam_core.camera import Frame, Intrinsics
from eslam_core.config import Config
from eslam_ros.conversions import (
    InvalidCameraInfoError,
    MalformedImageError,
    UnsupportedImageError,
    image_to_depth,
    image_to_rgb,
    intrinsics_from_camera_info,
    stamp_to_sec,
    to_time,
)
from eslam_ros.sync import ApproximateTimeSynchronizer

RGB, DEPTH = 0, 1  # stream indices in the synchronizer
STREAM_NAMES = ("rgb/image", "depth/image")


class SkipReason(str, Enum):
    """Why an input was not turned into a frame; the value is the counter's name in ~/status."""

    UNSUPPORTED_ENCODING = "unsupported_encoding"
    MALFORMED_IMAGE = "malformed_image"
    SIZE_MISMATCH = "size_mismatch"
    NO_CAMERA_INFO = "no_camera_info"
    INVALID_CAMERA_INFO = "invalid_camera_info"  # counts camera-info messages, not frames
    INTRINSICS_CHANGED = "intrinsics_changed"
    NON_MONOTONIC_STAMP = "non_monotonic_stamp"  # counts image messages, not frames


@dataclass(frozen=True)
class AcceptedFrame:
    """A paired, converted and checked RGB-D frame, ready for the SLAM runtime."""

    frame: Frame
    stamp: Any  # builtin_interfaces/Time of the rgb image: the stamp of every output computed from it
    frame_id: str  # the rgb image's frame (the camera's optical frame)
    intrinsics: Intrinsics
    received: float  # time.monotonic() when the message completing the pair arrived
    odometry: Any = None  # REP 105 mode: the robot's odometry at the frame (a FrameOdometry), once the node has it


@dataclass(frozen=True)
class SkippedInput:
    reason: SkipReason
    message: str


@dataclass(frozen=True)
class StreamRestart:
    """Stamps jumped back by `jump` seconds (e.g. a bag started over): what follows is a new stream."""

    jump: float


PipelineEvent = Union[AcceptedFrame, SkippedInput, StreamRestart]


class InputPipeline:
    """Messages in, frames out: pairs rgb and depth images, converts them and checks them against the camera.

    Holds no ROS node, so the live node and the offline bag runner (`eslam bag run`) share it. Every problem is
    returned as a SkippedInput event (and counted in `skipped`) instead of raised.

    depth_scale: depth units per metre (None: by encoding, REP 118). fixed_intrinsics: use these instead of
    camera-info messages. time_jump_reset: a stamp at least this many seconds older than its stream's last one
    restarts the stream (None: such messages are skipped like any other non-monotonic stamp).
    """

    def __init__(
        self,
        *,
        queue_size: int = 10,
        max_interval: Optional[float] = 0.02,
        age_penalty: float = 0.1,
        depth_scale: Optional[float] = None,
        fixed_intrinsics: Optional[Intrinsics] = None,
        time_jump_reset: Optional[float] = 1.0,
    ) -> None:
        self.sync = ApproximateTimeSynchronizer(2, queue_size, max_interval, age_penalty)
        self.depth_scale = depth_scale
        self.fixed_intrinsics = fixed_intrinsics
        self.time_jump_reset = time_jump_reset
        self.camera_infos: dict[str, Intrinsics] = {}  # latest valid camera info per frame_id
        self.latest_info: Optional[Intrinsics] = None
        # The intrinsics of the first accepted frame (the map is built for them): later frames must have the same.
        self.intrinsics: Optional[Intrinsics] = fixed_intrinsics
        self.frames_accepted = 0
        self.pairs = 0
        self.skipped: dict[str, int] = {reason.value: 0 for reason in SkipReason}
        self._last_stamp: list[Optional[float]] = [None, None]
        self._received: list[float] = [0.0, 0.0]  # arrival of the newest message per stream
        # Pairs that came before any camera info (drivers start the streams together, in no particular order):
        # they wait, at most queue_size of them, and are assembled when the first camera info arrives.
        self._awaiting_info: deque[tuple[Any, Any, float]] = deque()

    # -------------------------------------------------------------------------------------------- inputs

    def add_camera_info(self, msg: Any) -> list[PipelineEvent]:
        try:
            intrinsics = intrinsics_from_camera_info(msg)
        except InvalidCameraInfoError as error:
            return [self._skip(SkipReason.INVALID_CAMERA_INFO, f"camera info on rgb/camera_info ignored: {error}")]
        self.camera_infos[msg.header.frame_id] = intrinsics
        self.latest_info = intrinsics
        events: list[PipelineEvent] = []
        while self._awaiting_info:
            events.append(self._assemble(*self._awaiting_info.popleft()))
        return events

    def add_image(self, stream: int, msg: Any, received: Optional[float] = None) -> list[PipelineEvent]:
        """Queue an rgb (stream RGB) or depth (stream DEPTH) image; returns the frames and skips it caused."""
        received = time.monotonic() if received is None else received
        stamp = stamp_to_sec(msg.header.stamp)
        events: list[PipelineEvent] = []
        last = self._last_stamp[stream]
        if last is not None and stamp < last:
            jump = last - stamp
            if self.time_jump_reset is None or jump < self.time_jump_reset:
                return [self._skip(
                    SkipReason.NON_MONOTONIC_STAMP,
                    f"{STREAM_NAMES[stream]} stamp {stamp:.6f} s is {jump:.6f} s older than the previous one: message "
                    f"skipped (the publisher's clock went back; restamp it or replay the bag in order)",
                )]
            events += self.flush()  # the old stream's last pair, then start afresh
            events.append(StreamRestart(jump))
            self._last_stamp = [None, None]
        self._last_stamp[stream] = stamp
        self._received[stream] = received
        for rgb_msg, depth_msg in self.sync.add(stream, stamp, msg):
            events += self._pair(rgb_msg, depth_msg, max(self._received))
        return events

    def flush(self) -> list[PipelineEvent]:
        """End of stream (or a pause): emit the pending pair(s). Stamps must still go on increasing afterwards."""
        events: list[PipelineEvent] = []
        for rgb_msg, depth_msg in self.sync.flush():
            events += self._pair(rgb_msg, depth_msg, max(self._received))
        while self._awaiting_info:
            rgb_msg = self._awaiting_info.popleft()[0]
            events.append(self._skip(SkipReason.NO_CAMERA_INFO, self._no_info_message(rgb_msg)))
        return events

    @property
    def unpaired(self) -> dict[str, int]:
        """Images dropped by the synchronizer because no partner close enough in time arrived."""
        return {"unpaired_rgb": self.sync.dropped[RGB], "unpaired_depth": self.sync.dropped[DEPTH]}

    # -------------------------------------------------------------------------------------------- pairs

    def _pair(self, rgb_msg: Any, depth_msg: Any, received: float) -> list[PipelineEvent]:
        """A pair from the synchronizer: assembled now, or held until the first camera info arrives."""
        self.pairs += 1
        if self.fixed_intrinsics is not None or self.latest_info is not None:
            return [self._assemble(rgb_msg, depth_msg, received)]
        self._awaiting_info.append((rgb_msg, depth_msg, received))
        if len(self._awaiting_info) > self.sync.queue_size:
            return [self._skip(SkipReason.NO_CAMERA_INFO, self._no_info_message(self._awaiting_info.popleft()[0]))]
        return []

    @staticmethod
    def _no_info_message(rgb_msg: Any) -> str:
        return (f"frame skipped: no camera info received yet for frame '{rgb_msg.header.frame_id}'; remap "
                f"rgb/camera_info to the colour camera's camera_info topic (or set eslam.camera.fx/fy/cx/cy/width/"
                f"height)")

    def _assemble(self, rgb_msg: Any, depth_msg: Any, received: float) -> PipelineEvent:
        try:
            rgb = image_to_rgb(rgb_msg)
            depth = image_to_depth(depth_msg, self.depth_scale)
        except UnsupportedImageError as error:
            return self._skip(SkipReason.UNSUPPORTED_ENCODING, f"frame skipped: {error}")
        except MalformedImageError as error:
            return self._skip(SkipReason.MALFORMED_IMAGE, f"frame skipped: {error}")
        height, width = rgb.shape[:2]
        if depth.shape != (height, width):
            return self._skip(
                SkipReason.SIZE_MISMATCH,
                f"frame skipped: rgb is {width}x{height} but depth is {depth.shape[1]}x{depth.shape[0]}; the depth "
                f"image must be registered to the colour image (e.g. realsense2_camera align_depth.enable:=true, "
                f"and remap depth/image to the aligned depth topic)",
            )
        frame_id = rgb_msg.header.frame_id
        intrinsics = self.fixed_intrinsics or self.camera_infos.get(frame_id) or self.latest_info
        if (intrinsics.width, intrinsics.height) != (width, height):
            return self._skip(
                SkipReason.SIZE_MISMATCH,
                f"frame skipped: images are {width}x{height} but the camera info says "
                f"{intrinsics.width}x{intrinsics.height}; remap rgb/camera_info to the camera_info of the rgb topic",
            )
        if self.intrinsics is None:
            self.intrinsics = intrinsics
        elif intrinsics != self.intrinsics:
            return self._skip(
                SkipReason.INTRINSICS_CHANGED,
                f"frame skipped: camera intrinsics changed from {self.intrinsics} to {intrinsics}; the map is built "
                f"with the first ones: restart the node to use the new calibration",
            )
        frame = Frame(index=self.frames_accepted, timestamp=stamp_to_sec(rgb_msg.header.stamp), rgb=rgb,
                      depth=depth, pose=None)
        self.frames_accepted += 1
        return AcceptedFrame(frame, to_time(rgb_msg.header.stamp), frame_id, intrinsics, received)

    def _skip(self, reason: SkipReason, message: str) -> SkippedInput:
        self.skipped[reason.value] += 1
        return SkippedInput(reason, message)


def configured_intrinsics(cfg: Config) -> Optional[Intrinsics]:
    """Intrinsics set in the configuration (eslam.camera.*), which then replace camera-info messages."""
    c = cfg.camera
    if c.fx is None:
        return None
    return Intrinsics(c.width, c.height, c.fx, c.fy, c.cx, c.cy)
