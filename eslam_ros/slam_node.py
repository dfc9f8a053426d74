"""The ESLAM ROS 2 node: RGB-D images in; poses, path, mesh and health out.

Data flow
    rgb/image   --+
                  +-- approximate-time pairing -- convert and check -- Frame -- runtime.submit
    depth/image --+          (InputPipeline)          ^
                                                      +-- latest rgb/camera_info (cached, not paired)
    runtime.poll()        -> ~/pose, ~/odom, TF      (a thread of its own: each pose as soon as it is made)
    runtime.trajectory()  -> ~/path                  (refined keyframe poses included, every path_period)
    runtime.mesh_snapshot() -> ~/mesh                (blocks that changed, meshed at nice 19: mesh_publication.py)
    runtime.health()      -> ~/status                (diagnostic_msgs/DiagnosticArray, every status_period)
    services ~/save_mesh, ~/save_trajectory, ~/save_checkpoint, ~/reset (std_srvs/Trigger)

Frames and conventions
    ESLAM poses are camera-to-world in the camera's *optical* frame (x right, y down, z forward): REP 103's
    `<camera>_optical_frame`, the frame_id drivers put on image headers. A published pose is the pose of the image
    header's frame_id in `map_frame`; `map_frame` is the optical frame of the first camera pose (so its y axis
    points down). Every output is stamped with the stamp of the rgb image it was computed from.

Anything wrong with an input (unsupported encoding, inconsistent sizes, no camera info yet, a stamp going back in
time) skips that frame with one throttled log line per kind of problem, and is counted in ~/status. The node
keeps running.

Run: `ros2 run eslam_ros slam_node --ros-args --params-file config/slam_node.yaml -r rgb/image:=...` or, after a
pip install, `slam_node --ros-args ...` (see docs/ros.md).
"""
from __future__ import annotations

import dataclasses
import math
import signal
import sys
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Odometry, Path as PathMsg
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import CameraInfo, Image
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from eslam_core.camera import Intrinsics
from eslam_core.config import Config, ConfigError
from eslam_core.atomic import failure_line, make_output_folder
from eslam_core.runtime import RuntimeCrashed, make_runtime
from eslam_core.tracking.information import PoseCovariance, covariance_at
from eslam_core.tracking.quality import degenerate_view
from eslam_ros.conversions import InvalidPoseError, path_cdr
from eslam_ros.mesh_publication import MESH_POLL_S, MeshPublication
from eslam_ros.node_params import (
    ESLAM_PREFIX,
    NodeParameterError,
    NodeSettings,
    config_from_parameters,
    config_parameters,
    base_config,
    check_odometry_mode,
    node_parameter_defaults,
    settings_from_parameters,
    unknown_eslam_parameters,
    unknown_parameter_error,
)
from eslam_ros.qos import input_qos, latched_qos, output_qos, use_shipped_fastdds_profile

from eslam_ros.input_pipeline import (DEPTH, RGB, STREAM_NAMES, AcceptedFrame, InputPipeline, PipelineEvent,
                                     SkippedInput, StreamRestart, configured_intrinsics)
from eslam_ros.node_threads import CallbackGate, LogThrottle, PeriodicThread, StopRequest, node_executor, spin_once
from eslam_ros.pose_messages import odometry, pose_stamped, twist_between
from eslam_ros.diagnostics import InputMonitor, StatusInputs, diagnostic_array, status_level, status_marker
from eslam_ros.robot_odometry import FrameOdometry, RobotOdometry, frame_with_odometry
from eslam_ros.start_queue import StartQueue, frame_bytes
from eslam_ros.tf_chain import TfOdometry, TfOutput, base_in_map, map_to_odom, select_setup, transform_stamped

EXIT_OK, EXIT_FAILED, EXIT_BAD_PARAMETERS, EXIT_INTERRUPTED = 0, 1, 2, 130
# At shutdown with the live policy: how long the frame in progress may take before the runtime is stopped.
LIVE_DRAIN_TIMEOUT_S = 10.0
POSE_WAIT_S = 0.05  # the pose thread's longest wait for a pose (it checks for a stop request in between)


# ================================================================================================= input pipeline


# ================================================================================================= the node


def _refused(request: Any, response: Any) -> Any:
    response.success, response.message = False, "the node is shutting down or failed; see its log"
    return response


@dataclass
class _Submitted:
    """What the node remembers of a frame handed to the runtime, until its pose comes back."""

    stamp: Any
    frame_id: str
    received: float


@dataclass
class _Latency:
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
class _Outputs:
    """Counters of what the node published (for ~/status)."""

    poses: int = 0
    paths: int = 0
    poses_invalid: int = 0  # poses that were not rigid transforms (NaN, not a rotation): not published, counted
    poses_lost: int = 0  # frames tracked while lost: ~/odom only, with an unknown covariance
    restarts: int = 0
    dropped_while_starting: int = 0
    latency: _Latency = field(default_factory=_Latency)
    # The node's own share of the work (seconds, summed): image callbacks (pairing, conversion, hand-over to the
    # runtime) and pose publication (poll, messages, TF).
    input_seconds: float = 0.0
    output_seconds: float = 0.0


class SlamNode(Node):
    """The ROS 2 node; see the module docstring for its topics, services and conventions."""

    def __init__(self, node_name: str = "slam_node", **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        self.configure_slam()
        self.activate_slam()

    # The plain node runs configure + activate in its constructor; the lifecycle node (eslam_ros.lifecycle_node)
    # runs them as transitions. Inputs and periodic outputs belong to "active"; publishers, services and the map
    # live from configure to cleanup.

    def configure_slam(self) -> None:
        """Read the parameters, make the input pipeline, the publishers and the services (no input yet)."""
        self.settings, self.config = self._declare_parameters()
        s = self.settings
        self.tf_setup = select_setup(s)
        self.output_dir = Path(s.output_dir).expanduser()
        self.pipeline = InputPipeline(
            queue_size=s.sync_queue_size,
            max_interval=s.sync_max_interval or None,
            age_penalty=s.sync_age_penalty,
            depth_scale=s.depth_scale or None,
            fixed_intrinsics=configured_intrinsics(self.config),
            time_jump_reset=s.time_jump_reset or None,
        )
        # The runtime needs the camera, so it starts with the first accepted frame, on a thread of its own (spawning
        # workers takes seconds, and the input callbacks must keep taking messages meanwhile). Frames accepted while
        # it starts wait in `_held` (offline: all of them, up to start_queue_bytes; live: the newest 30).
        self.runtime = None
        self._starter: Optional[threading.Thread] = None
        self._load_map = bool(self.settings.map_file)  # the next runtime starts from map_file
        self._held: StartQueue[AcceptedFrame] = StartQueue(s.policy, s.start_queue_bytes)
        self.failed: Optional[str] = None  # set when the runtime crashed: the node then stops with an error
        self.active = False
        self.outputs = _Outputs()
        self._throttle = LogThrottle(s.log_throttle)
        self.inputs = InputMonitor()
        # Pose bookkeeping, shared by the input thread and the services' thread (reset).
        self._lock = threading.Lock()
        self._submitted: dict[int, _Submitted] = {}
        self._frame_odometry: dict[int, FrameOdometry] = {}  # REP 105 mode: per submitted frame, until its pose
        self._map_started = False  # REP 105 mode: the first frame of a map is seeded with its odometry pose
        self._camera_frame = ""  # the image frame_id (the camera optical frame), once known
        self._previous_pose: Optional[tuple[np.ndarray, float]] = None
        self._last_position = np.zeros(3)  # of the camera in map_frame, where the status text floats
        self._lost = False  # the newest pose update said the camera is lost
        self._degraded: Optional[str] = None  # the newest pose update was degraded: its free direction
        self._last_image = time.monotonic()
        self._skipped_at_last_status = 0
        self._odometry_problems_at_last_status: dict[str, int] = {}
        self._poses_at_last_status = (0, time.monotonic())

        # Inputs and path in one group (in order); services, odometry and status in their own (these matter where the
        # node runs on a MultiThreadedExecutor; poses and mesh have threads of their own).
        self._io = MutuallyExclusiveCallbackGroup()
        self._slow = MutuallyExclusiveCallbackGroup()
        # rclpy's executor serves one exclusive group's ready entities timers first, then subscriptions, in creation
        # order, and skips the rest while the group is busy: in the inputs' group, the odometry subscription and
        # the status timer were served only when nothing else was ready, i.e. not at all under load.
        self._odometry_in = MutuallyExclusiveCallbackGroup()
        self._status = MutuallyExclusiveCallbackGroup()
        self.gate = CallbackGate(on_error=self._on_callback_error)
        gate = self.gate.wrap
        self.pose_pub = self.create_publisher(PoseStamped, "~/pose", output_qos())
        self.odom_pub = self.create_publisher(Odometry, "~/odom", output_qos())
        self.path_pub = self.create_publisher(PathMsg, "~/path", output_qos(1))
        self.mesh = MeshPublication(
            lambda data: self.mesh_pub.publish(data), s.map_frame, lambda: self.get_clock().now().to_msg(),
            self.get_logger(), resolution=self._mesh_resolution() or self.config.mesh.resolution,
            block_size=s.mesh_block_size, period=s.mesh_period, budget_s=s.mesh_time_budget,
            triangle_budget=s.mesh_triangle_budget, nice=s.mesh_nice, duty=s.mesh_duty)
        # A new subscriber gets every block of the mesh (messages carry only changes): see mesh_publication.py.
        self.mesh_pub = self.create_publisher(MarkerArray, "~/mesh", latched_qos(), event_callbacks=(
            PublisherEventCallbacks(matched=self.mesh.subscriber_matched)))
        self.status_pub = self.create_publisher(DiagnosticArray, "~/status", output_qos())
        # The same status where diagnostic_aggregator and rqt_robot_monitor look.
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", output_qos())
        self.status_marker_pub = self.create_publisher(Marker, "~/status_marker", output_qos(1))
        self.tf_output = TfOutput(self, self.tf_setup.tf_output)
        self.map_to_odom_pub = (self.create_publisher(TransformStamped, "~/map_to_odom", output_qos())
                                if self.tf_setup.rep105 else None)
        tf_odometry = TfOdometry(self, s.odom_frame, s.base_frame) if "tf" in (
            self.tf_setup.odometry, self.tf_setup.extrinsic) else None
        self.odometry: Optional[RobotOdometry[AcceptedFrame]] = RobotOdometry(
            s, self.tf_setup, tf_odometry) if self.tf_setup.rep105 else None

        self._configured_entities: list = [self.create_timer(s.status_period, gate(self._publish_status),
                                                             callback_group=self._status)]
        for name, handler in (("~/save_mesh", self._srv_save_mesh), ("~/save_trajectory", self._srv_save_trajectory),
                              ("~/save_checkpoint", self._srv_save_checkpoint), ("~/reset", self._srv_reset),
                              ("~/load_map", self._srv_load_map)):
            self._configured_entities.append(
                self.create_service(Trigger, name, gate(handler, when_closed=_refused), callback_group=self._slow))
        self._active_entities: list = []

        if not getattr(self, "_refusing_parameter_changes", False):
            self.add_on_set_parameters_callback(self._refuse_parameter_changes)
            self._refusing_parameter_changes = True
        self.get_logger().info(f"TF: {self.tf_setup.describe(s)}")
        self.get_logger().info(
            f"ESLAM node ready: {'config file ' + s.config_file if s.config_file else 'preset ' + s.preset}, "
            f"{s.workers} worker(s), {s.policy} policy, tracking mode {self.config.tracking.mode}, input QoS "
            f"{s.input_qos}, poses in '{s.map_frame}', outputs to {self.output_dir.resolve()}; waiting for "
            f"rgb/image, depth/image and rgb/camera_info" + (" and odom" if self.tf_setup.odometry == "topic" else "")
        )

    def activate_slam(self) -> None:
        """Subscribe to the inputs and start the periodic outputs (the runtime starts with the first frame)."""
        s, gate = self.settings, self.gate.wrap
        qos_in = input_qos(s.input_qos, s.input_queue_depth)
        self.inputs = InputMonitor()
        self._subscriptions_in = [
            self.create_subscription(Image, "rgb/image", gate(lambda m: self._on_image(RGB, m)), qos_in,
                                     callback_group=self._io),
            self.create_subscription(Image, "depth/image", gate(lambda m: self._on_image(DEPTH, m)), qos_in,
                                     callback_group=self._io),
            self.create_subscription(CameraInfo, "rgb/camera_info", gate(self._on_camera_info), qos_in,
                                     callback_group=self._io),
        ]
        if self.tf_setup.odometry == "topic":
            self._subscriptions_in.append(self.create_subscription(
                Odometry, "odom", gate(self._on_odometry), input_qos(s.input_qos, max(s.input_queue_depth, 100)),
                callback_group=self._odometry_in))
        timers = [self.create_timer(s.path_period, gate(self._publish_path), callback_group=self._io),
                  self.create_timer(min(0.1, s.sync_idle_flush or 0.1), gate(self._tick_inputs),
                                    callback_group=self._io)]
        if self.odometry is not None:
            timers.append(self.create_timer(0.02, gate(self._release_odometry), callback_group=self._io))
        self._active_entities = self._subscriptions_in + timers
        self.active = True
        # Poses go out from a thread that waits for them (no polling delay, no executor wake-ups 100 times a
        # second), the mesh from one of its own (a map snapshot takes up to seconds): neither holds the executor.
        self._threads = [PeriodicThread("eslam-poses", 0.0, self._pose_out)]
        if s.mesh_period > 0:
            self._threads.append(PeriodicThread("eslam-mesh-out", min(MESH_POLL_S, s.mesh_period),
                                               gate(self._publish_mesh)))

    def deactivate_slam(self) -> None:
        """Stop taking input and publishing periodically; the runtime and its map stay (tracking and mapping pause
        once the frames already submitted are done, at most LIVE_DRAIN_TIMEOUT_S)."""
        self.active = False
        for entity in self._active_entities:
            self._destroy(entity)
        self._active_entities = []
        self._stop_threads()
        if self.runtime is not None and not self.failed:
            self._drain(LIVE_DRAIN_TIMEOUT_S)

    def destroy_slam_entities(self) -> None:
        """Cleanup: every publisher, service and timer the node made (after `finish`)."""
        if self.active:
            self.deactivate_slam()
        for entity in self._configured_entities + [self.pose_pub, self.odom_pub, self.path_pub, self.mesh_pub,
                                                   self.status_pub, self.diagnostics_pub, self.status_marker_pub,
                                                   self.map_to_odom_pub]:
            if entity is not None:
                self._destroy(entity)
        self._configured_entities = []

    def _destroy(self, entity: Any) -> None:
        kind = type(entity).__name__
        destroy = {"Subscription": self.destroy_subscription, "Timer": self.destroy_timer,
                   "Service": self.destroy_service}.get(kind, self.destroy_publisher)
        destroy(entity)

    # ------------------------------------------------------------------------------------------ parameters

    def _declare_parameters(self) -> tuple[NodeSettings, Config]:
        """Declare every node and ESLAM parameter (so `ros2 param list` shows them) and read them back."""
        dynamic = dict(dynamic_typing=True)  # types are checked by settings_from_parameters / the config
        self.declare_node_parameters()
        settings = settings_from_parameters(
            {name: self.get_parameter(name).value for name in node_parameter_defaults()})

        base = base_config(settings)
        # rclpy silently ignores overrides of undeclared parameters: catch misspelt eslam.* keys here.
        given = getattr(self, "_parameter_overrides", {})
        unknown = unknown_eslam_parameters(given, base)
        if unknown:
            raise unknown_parameter_error(unknown[0], base)
        defaults = config_parameters(base)
        for name, default in defaults.items():
            if not self.has_parameter(name):
                self.declare_parameter(name, default, ParameterDescriptor(
                    description=f"ESLAM setting {name[len(ESLAM_PREFIX):]} (see eslam_core.config)", **dynamic))
        origin = f"config file {settings.config_file}" if settings.config_file else f"preset '{settings.preset}'"
        config = config_from_parameters({name: self.get_parameter(name).value for name in defaults},
                                        f"ROS parameters eslam.* over {origin}")
        check_odometry_mode(settings, config)
        return settings, config

    def declare_node_parameters(self) -> None:
        """The node settings (not the eslam.* ones, whose defaults depend on the preset); declared once, so a
        lifecycle node configured again keeps them."""
        for name, (default, doc) in node_parameter_defaults().items():
            if not self.has_parameter(name):
                self.declare_parameter(name, default, ParameterDescriptor(description=doc, dynamic_typing=True))

    # A lifecycle node takes parameter changes while unconfigured (they are read at the next configure).
    parameters_open = False

    def _refuse_parameter_changes(self, parameters: list) -> SetParametersResult:
        if self.parameters_open:
            return SetParametersResult(successful=True)
        names = ", ".join(p.name for p in parameters)
        return SetParametersResult(successful=False, reason=(
            f"{names}: parameters are read at start-up only; restart the node with the new value"))

    # ------------------------------------------------------------------------------------------ inputs

    def _on_camera_info(self, msg: CameraInfo) -> None:
        self._handle(self.pipeline.add_camera_info(msg))

    def _on_image(self, stream: int, msg: Image) -> None:
        start = self._last_image = time.monotonic()
        self.inputs.arrived(STREAM_NAMES[stream], self._last_image)
        self._handle(self.pipeline.add_image(stream, msg, self._last_image))
        self.outputs.input_seconds += time.monotonic() - start

    def _on_odometry(self, msg: Odometry) -> None:
        self.inputs.arrived("odom")
        refused = self.odometry.add_message(msg, time.monotonic())
        if refused and self._throttle.allow("odom_rejected"):
            self.get_logger().warning(f"{refused} [odom_rejected: {self.odometry.counts['odom_rejected']} so far]")

    def _accept(self, accepted: AcceptedFrame) -> None:
        """A frame from the pipeline: to the runtime, in REP 105 mode once its odometry is settled."""
        self.inputs.arrived("pair")
        self._camera_frame = accepted.frame_id
        if self.odometry is None:
            self._submit(accepted)
            return
        self.odometry.push(accepted.frame.timestamp, accepted.frame_id, accepted, time.monotonic())
        self._release_odometry()

    def _release_odometry(self, flush: bool = False) -> None:
        for accepted, odometry in self.odometry.release(time.monotonic(), flush):
            frame = self._with_odometry(accepted, odometry)
            if frame is not None:
                self._submit(frame)

    def _with_odometry(self, accepted: AcceptedFrame, odometry: FrameOdometry) -> Optional[AcceptedFrame]:
        if odometry.problem is not None or odometry.jumped:
            key = odometry.problem.value if odometry.problem is not None else "jump"
            if self._throttle.allow(f"odom_{key}"):
                self.get_logger().warning(f"frame at {accepted.frame.timestamp:.3f}: {odometry.message} "
                                          f"[{self.odometry.counts}]")
        frame = frame_with_odometry(accepted.frame, odometry, self._map_started,
                                    self.config.tracking.mode == "external")
        if frame is None:
            self.odometry.counts["odom_frames_skipped"] += 1
            return None
        if odometry.problem is None:
            self._map_started = True
            with self._lock:
                self._frame_odometry[accepted.frame.index] = odometry
        return dataclasses.replace(accepted, frame=frame)

    def _tick_inputs(self) -> None:
        """Frames held while the runtime started go to it once it runs; after `sync_idle_flush` s without an image
        the stream ended (or paused), so the pending pair will not get a better match."""
        if self.runtime is not None:
            self._submit_held()
        idle = self.settings.sync_idle_flush
        if idle > 0 and self.pipeline.sync.pending and time.monotonic() - self._last_image > idle:
            self._handle(self.pipeline.flush())

    def _handle(self, events: Sequence[PipelineEvent]) -> None:
        for event in events:
            if isinstance(event, AcceptedFrame):
                self._accept(event)
            elif isinstance(event, SkippedInput):
                if self._throttle.allow(event.reason.value):
                    self.get_logger().warning(f"{event.message} [{event.reason.value}: "
                                              f"{self.pipeline.skipped[event.reason.value]} so far]")
            elif isinstance(event, StreamRestart):
                self.outputs.restarts += 1
                self.get_logger().warning(f"image stamps jumped back by {event.jump:.3f} s (a bag started over?): "
                                          f"resetting the map")
                self._reset_runtime()

    def _start_runtime(self, intrinsics: Intrinsics) -> None:
        """Runs on the starter thread; the pipeline has fixed the intrinsics to these."""
        s = self.settings
        self.get_logger().info(f"starting the SLAM runtime ({s.workers} worker(s), {s.policy}) for {intrinsics}")
        checkpoint = s.map_file if self._load_map else None
        self._load_map = False
        try:
            runtime = make_runtime(self.config, intrinsics, workers=s.workers, policy=s.policy, checkpoint=checkpoint)
            runtime.start()
        except (RuntimeCrashed, ValueError) as error:
            self._fail(f"the SLAM runtime did not start: {error}")
            return
        self.runtime = runtime
        self.get_logger().info("SLAM runtime running")

    def _submit(self, accepted: AcceptedFrame) -> None:
        if self.failed:
            return
        if self.runtime is None:
            if self._starter is None:
                self._starter = threading.Thread(target=self._start_runtime, args=(accepted.intrinsics,),
                                                 name="eslam-runtime-start", daemon=True)
                self._starter.start()
            dropped = self._held.push(accepted, frame_bytes(accepted.frame))
            if dropped:
                self.outputs.dropped_while_starting += dropped
                if self._throttle.allow("dropped_while_starting"):
                    self.get_logger().warning(
                        f"{self.outputs.dropped_while_starting} frame(s) dropped while the SLAM runtime starts: "
                        + (f"more than start_queue_bytes = {self.settings.start_queue_bytes} bytes queued; raise it"
                           if self.settings.policy == "offline" else "the live policy keeps the newest 30"))
            return
        self._submit_held()
        self._submit_now(accepted)

    def _submit_held(self) -> None:
        while self._held and self.runtime is not None and not self.failed:
            self._submit_now(self._held.popleft())

    def _submit_now(self, accepted: AcceptedFrame) -> None:
        with self._lock:
            self._submitted[accepted.frame.index] = _Submitted(accepted.stamp, accepted.frame_id, accepted.received)
        try:
            self.runtime.submit(accepted.frame)
        except RuntimeCrashed as error:
            self._fail(f"the SLAM runtime crashed: {error}")

    # ------------------------------------------------------------------------------------------ outputs

    def _pose_out(self) -> None:
        if self.runtime is None or self.failed or self.gate.closed:
            time.sleep(POSE_WAIT_S)
            return
        try:
            self._publish_poses(wait=POSE_WAIT_S)
        except Exception as error:  # noqa: BLE001 - reported, and the node goes on (or stops, if SLAM died)
            self._on_callback_error(error)

    def _stop_threads(self) -> None:
        """After this, poses are published by the caller (`_drain`) only, so they stay in order."""
        for thread in getattr(self, "_threads", []):
            thread.stop()
        self._threads = []

    def _publish_poses(self, wait: float = 0.0) -> None:
        if self.runtime is None or self.failed:
            return
        try:
            updates = self.runtime.poll(timeout=wait)
        except RuntimeCrashed as error:
            self._fail(f"the SLAM runtime crashed: {error}")
            return
        start = time.monotonic()
        for update in updates:
            self._publish_pose(update)
        self.outputs.output_seconds += time.monotonic() - start

    def _publish_pose(self, update: Any) -> None:
        with self._lock:
            submitted = self._submitted.pop(update.index, None)
            frame_odometry = self._frame_odometry.pop(update.index, None)
            # Frames before this one that got no pose were dropped by the live policy: forget them.
            for index in [i for i in self._submitted if i < update.index]:
                del self._submitted[index]
            for index in [i for i in self._frame_odometry if i < update.index]:
                del self._frame_odometry[index]
            previous = self._previous_pose
            self._previous_pose = (update.pose, update.timestamp)
        if submitted is None:  # a frame from before a reset
            return
        stamp, map_frame = submitted.stamp, self.settings.map_frame
        output = self._output_pose(update.pose, submitted.frame_id)
        if output is None:
            return
        output_pose, child = output
        twist = (np.zeros(3), np.zeros(3))
        if previous:
            previous_output = self._output_pose(previous[0], submitted.frame_id)
            twist = twist_between(previous_output[0], previous[1], output_pose, update.timestamp)
        try:
            covariance = None if update.covariance is None else covariance_at(
                update.covariance, output_pose[:3, 3] - update.pose[:3, 3])  # (the base's, with pose_frame base)
            pose, odom = pose_stamped(output_pose, stamp, map_frame), odometry(
                output_pose, twist, stamp, map_frame, child, update.quality, update.lost, covariance)
            tf = self._tf_of(update.pose, frame_odometry, stamp, child)
        except InvalidPoseError as error:  # NaN or not a rotation at all (drift is re-orthonormalised): skip it
            self.outputs.poses_invalid += 1
            if self._throttle.allow("invalid_pose"):
                self.get_logger().warning(
                    f"pose of frame {update.index} not published: {error} [{self.outputs.poses_invalid} invalid "
                    f"poses skipped, {self.outputs.poses} published so far; publishing goes on]")
            return
        self._lost = update.lost
        self._degraded = degenerate_view(PoseCovariance(update.covariance)) if update.degraded and \
            update.covariance is not None else None
        if update.lost:  # no pose to act on: ~/odom says so with its covariance, ~/pose and TF wait
            self.odom_pub.publish(odom)
            self.outputs.poses_lost += 1
            return
        self.pose_pub.publish(pose)
        self.odom_pub.publish(odom)
        self._last_position = update.pose[:3, 3].copy()
        if tf is not None:
            self.tf_output.send(tf)
            if self.map_to_odom_pub is not None:
                self.map_to_odom_pub.publish(tf)
        self.outputs.poses += 1
        self.outputs.latency.add(time.monotonic() - submitted.received)

    def _output_pose(self, camera_pose: np.ndarray, frame_id: str) -> Optional[tuple[np.ndarray, str]]:
        """(pose, child frame) of ~/pose, ~/odom and ~/path: the camera's, or the base's with pose_frame base (None
        while the extrinsic is unknown)."""
        s = self.settings
        if s.pose_frame == "camera":
            return camera_pose, s.tf_child_frame or frame_id
        base_camera = self.odometry.base_camera(frame_id)
        if base_camera is None:
            if self._throttle.allow("no_extrinsic"):
                self.get_logger().warning(f"pose not published: no TF {s.base_frame} -> {frame_id} yet (pose_frame "
                                          f"base needs the camera extrinsic)")
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

    def _publish_path(self) -> None:
        if self.runtime is None or self.failed:
            return
        timestamps, poses = self.runtime.trajectory(self.settings.path_max_poses)
        finite = np.isfinite(poses).all(axis=(1, 2)) if len(timestamps) else np.zeros(0, bool)
        if finite.any() and self.settings.pose_frame == "base":
            base_camera = self.odometry.base_camera(self._camera_frame)
            if base_camera is None:
                return
            poses = poses.copy()
            poses[finite] = base_in_map(poses[finite], base_camera)
        if finite.any():
            self.path_pub.publish(path_cdr(timestamps[finite], poses[finite], self.settings.map_frame))
            self.outputs.paths += 1

    def _publish_mesh(self) -> None:
        if self.runtime is None or self.failed:
            return
        self.mesh.tick(self.runtime)  # the blocks that changed, meshed in a low-priority process

    def _mesh_resolution(self) -> Optional[float]:
        return self.settings.mesh_resolution or None

    def state(self) -> str:
        if self.failed:
            return "failed"
        if not self.active:
            return "inactive"
        return "running" if self.runtime else "starting" if self._starter else "waiting"

    def ready(self) -> bool:
        """A frame published now is taken without loss: the node is active and sees a publisher on each input,
        and the runtime runs or the start-up queue has room (what `eslam bag play --wait-ready` waits for)."""
        if not self.active or self.failed:
            return False
        watched = [sub for sub in self._subscriptions_in
                   if not (sub.topic_name.endswith("camera_info") and self.pipeline.fixed_intrinsics)]
        # Matched by this subscription, not only known to the graph: a subscription created on activation sees
        # publishers the graph knew before it has matched them, and a reliable message sent in between is lost.
        if not all(sub.get_publisher_count() for sub in watched):
            return False
        return self.runtime is not None or self._held.has_room(self._held.bytes // max(len(self._held), 1))

    def health(self) -> dict[str, Any]:
        """The runtime's health figures and the node's counters, as published on ~/status."""
        values: dict[str, Any] = {"runtime": self.state(), "ready": self.ready(),
                                  "tf_mode": self.tf_setup.describe(self.settings, self._camera_frame or
                                                                    "<image frame_id>"),
                                  "tracking_mode": self.config.tracking.mode}
        if self.runtime is not None and not self.failed:
            values.update(self.runtime.health().as_dict())
        values["frames_accepted"] = self.pipeline.frames_accepted
        values["pairs"] = self.pipeline.pairs
        # (copied at once: the inputs' thread may add a key meanwhile)
        values.update(dict(self.pipeline.unpaired))
        skipped = dict(self.pipeline.skipped)
        values.update({f"skipped_{reason}": count for reason, count in skipped.items()})
        values["skipped_total"] = sum(skipped.values())
        values["poses_published"] = self.outputs.poses
        values["poses_invalid"] = self.outputs.poses_invalid
        values["poses_lost"] = self.outputs.poses_lost
        values.update(self.mesh.status())
        values["stream_restarts"] = self.outputs.restarts
        values["frames_dropped_while_starting"] = self.outputs.dropped_while_starting
        values["start_queue_frames"] = len(self._held)
        values["start_queue_bytes"] = self._held.bytes
        values["start_queue_peak_bytes"] = self._held.peak_bytes
        values["start_queue_budget_bytes"] = self.settings.start_queue_bytes
        values["input_rate_hz"] = self.inputs.rate()
        for name in self._watched_inputs():
            values[f"seconds_since_{name.replace('/', '_')}"] = self.inputs.silent_for(name)
        if self.odometry is not None:
            values.update(dict(self.odometry.counts))
            values["frames_waiting_for_odometry"] = len(self.odometry)
        values["latency_ms_receive_to_pose_last"] = 1000 * self.outputs.latency.last
        values["latency_ms_receive_to_pose_mean"] = 1000 * self.outputs.latency.mean
        values["latency_ms_receive_to_pose_max"] = 1000 * self.outputs.latency.worst
        values["node_ms_per_pair_in"] = 1000 * self.outputs.input_seconds / max(self.pipeline.pairs, 1)
        values["node_ms_per_pose_out"] = 1000 * self.outputs.output_seconds / max(self.outputs.poses, 1)
        return values

    def _publish_status(self) -> None:
        values = self.health()
        now = time.monotonic()
        poses_before, since = self._poses_at_last_status
        values["pose_rate_hz"] = (self.outputs.poses - poses_before) / max(now - since, 1e-9)
        self._poses_at_last_status = (self.outputs.poses, now)
        skipped_now = values["skipped_total"] - self._skipped_at_last_status
        self._skipped_at_last_status = values["skipped_total"]
        problems = {key: values.get(key, 0) for key in ("odom_missing", "odom_gaps", "odom_jumps", "odom_rejected")}
        problems_now = {key: count - self._odometry_problems_at_last_status.get(key, 0)
                        for key, count in problems.items()}
        self._odometry_problems_at_last_status = problems
        s = self.settings
        level, summary = status_level(StatusInputs(
            failed=self.failed, state=values["runtime"], poses=self.outputs.poses,
            silent_s={name: self.inputs.silent_for(name, now) for name in self._watched_inputs()} if self.active
            else {}, pair_rate_hz=values["input_rate_hz"], measured_for_s=now - self.inputs.started,
            skipped_now=skipped_now, odometry_problems_now=problems_now if self.odometry else {},
            lost=f"quality {values.get('tracking_quality', 0.0):.2f}" if self._lost else None,
            degraded=self._degraded),
            s.no_input_timeout, s.min_input_rate)
        msg = diagnostic_array(self.diagnostic_name(), s.diagnostics_hardware_id, level, summary, values,
                               self.get_clock().now().to_msg())
        self.status_pub.publish(msg)
        self.diagnostics_pub.publish(msg)
        # Above the camera: map "up" is z with REP 105 (map = odom), -y in camera mode (map = optical frame).
        up = np.array([0.0, 0.0, 0.4]) if self.tf_setup.rep105 else np.array([0.0, -0.4, 0.0])
        self.status_marker_pub.publish(status_marker(self.diagnostic_name(), level, summary, self._last_position + up,
                                                     s.map_frame, msg.header.stamp))

    def diagnostic_name(self) -> str:
        """The status's name: the same for the node's whole life, so that diagnostic_aggregator can group it."""
        return f"{self.get_name()}: ESLAM"

    def _watched_inputs(self) -> list[str]:
        """Inputs whose silence is a warning: the images, and the odometry topic when there is one."""
        return list(STREAM_NAMES) + (["odom"] if self.tf_setup.odometry == "topic" else [])

    # ------------------------------------------------------------------------------------------ services

    def _srv_save_mesh(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        return self._save(response, "mesh.ply", lambda rt, p: rt.save_mesh(p, resolution=self._mesh_resolution()))

    def _srv_save_trajectory(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        return self._save(response, "trajectory.txt", lambda rt, p: rt.save_trajectory(p))

    def _srv_save_checkpoint(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        return self._save(response, "checkpoint.pt", lambda rt, p: rt.save_checkpoint(p))

    def _srv_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self.runtime is None:
            response.success, response.message = False, "nothing to reset: no frame received yet"
            return response
        self._reset_runtime()
        response.success, response.message = True, "map and trajectory cleared; the next frame starts a new map"
        return response

    def _srv_load_map(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Drop the current map and continue in the one of `map_file` (from the next frame, relocalized), once the
        file passed every check its load makes (slam.read_loadable: intact, this version, this configuration's model
        settings and image scale, and the session's camera once a frame gave it); a file that fails one is refused
        with that line and the current map goes on, untouched."""
        from eslam_core.slam import read_loadable

        path = self.settings.map_file
        if not path:
            response.success, response.message = False, ("no map_file parameter set: start the node with "
                                                         "map_file:=<checkpoint.pt> (parameters are read at start-up)")
            return response
        camera = self.pipeline.intrinsics  # the session's camera (the next runtime's), None before the first frame
        try:
            read_loadable(path, self.config, camera)
        except ValueError as error:  # CheckpointError, one line: what is wrong and what to do
            kept = "the current map goes on" if self.runtime is not None else "nothing changed"
            response.success, response.message = False, f"{error} (map not loaded, {kept})"
            self.get_logger().warning(f"~/load_map refused: {response.message}")
            return response
        with self._lock:
            old, self.runtime = self.runtime, None
            if self._starter is not None:
                self._starter.join()
                old, self.runtime = old or self.runtime, None
            self._starter, self._load_map = None, True
            self._submitted.clear()
            self._frame_odometry.clear()
            self._previous_pose = None
            self.mesh.reset()
        if old is not None:
            old.close(drain=False)
        response.success, response.message = True, f"{path}: the next frame starts in this map" + (
            "" if camera is not None else " (its camera is checked against the first frame's: none received yet)")
        self.get_logger().info(f"~/load_map: {response.message}")
        return response

    def _save(self, response: Trigger.Response, name: str, save: Any) -> Trigger.Response:
        if self.runtime is None or self.failed:
            response.success = False
            response.message = self.failed or "nothing to save yet: no frame has been received"
            return response
        path = self.output_dir / name
        try:
            make_output_folder(path.parent)
            save(self.runtime, path)
        except (ValueError, OSError, RuntimeCrashed) as error:
            # One line (a full disk: the space needed and what to do); an older file of that name is intact.
            response.success, response.message = False, failure_line(path, error)
            self.get_logger().error(response.message)
            return response
        response.success, response.message = True, str(path.resolve())
        self.get_logger().info(f"wrote {path}")
        return response

    def _reset_runtime(self) -> None:
        with self._lock:
            if self.runtime is not None:
                self.runtime.reset()
            self._submitted.clear()
            self._frame_odometry.clear()
            self._map_started = False
            self._previous_pose = None
            self.mesh.reset()
        if self.odometry is not None:
            self.odometry.reset()

    # ------------------------------------------------------------------------------------------ lifecycle

    def _fail(self, message: str) -> None:
        if self.failed is None:
            self.get_logger().fatal(message)
        self.failed = message

    def _on_callback_error(self, error: BaseException) -> None:
        if isinstance(error, RuntimeCrashed):
            self._fail(f"the SLAM runtime crashed: {error}")
        else:
            self.get_logger().error(f"unexpected error in a callback (the node goes on): {type(error).__name__}: "
                                    f"{error}\n{traceback.format_exc()}")

    def finish(self, save: bool) -> int:
        """End of the run: wait for callbacks in progress (a mesh, a service), hand over the pending pair, publish
        the last poses, stop the runtime and save trajectory, checkpoint and mesh from its final state.

        With the offline policy every submitted frame is tracked first (a second Ctrl-C abandons that); with the
        live policy the frame in progress is. Returns the process exit status.
        """
        if not self.gate.close(timeout=120.0):
            self.get_logger().warning("a callback is still running after 120 s; shutting down anyway")
        self._stop_threads()
        self.mesh.close()
        if self._starter is not None:
            self._starter.join()  # the runtime bounds its own start-up time
        runtime = self.runtime
        if runtime is None:
            return EXIT_FAILED if self.failed else EXIT_OK
        try:
            if not self.failed:
                self._handle(self.pipeline.flush())
                if self.odometry is not None:
                    self._release_odometry(flush=True)
                self._submit_held()
                self._drain(math.inf if self.settings.policy == "offline" else LIVE_DRAIN_TIMEOUT_S)
            runtime.close(timeout=LIVE_DRAIN_TIMEOUT_S)
        except RuntimeCrashed as error:
            self._fail(f"the SLAM runtime crashed: {error}")
            return EXIT_FAILED
        if save and not self.failed:
            # Small and most valuable first: on a disk that fills up, the trajectory is what still gets written;
            # each failure is one line and does not stop the next output.
            outputs = (("trajectory.txt", runtime.save_trajectory), ("checkpoint.pt", runtime.save_checkpoint),
                       ("mesh.ply", lambda p: runtime.save_mesh(p, resolution=self._mesh_resolution())))
            for name, save_one in outputs:
                path = self.output_dir / name
                try:
                    make_output_folder(path.parent)
                    save_one(path)
                    self.get_logger().info(f"wrote {path}")
                except (ValueError, OSError) as error:
                    self.get_logger().error(failure_line(path, error))
        return EXIT_FAILED if self.failed else EXIT_OK

    def abort(self) -> None:
        """Stop the runtime at once, saving nothing (a second Ctrl-C)."""
        self._stop_threads()
        self.mesh.close()
        if self.runtime is not None:
            try:
                self.runtime.close(timeout=0, drain=False)
            except RuntimeCrashed:
                pass

    def _drain(self, timeout: float) -> None:
        """Publish poses until every submitted frame got one (or was dropped), or `timeout` seconds passed."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not self.failed:
            self._publish_poses()
            health = self.runtime.health()
            if health.frames_tracked + health.frames_dropped >= health.frames_received:
                self._publish_poses()
                return
            time.sleep(0.02)


# ================================================================================================= process


def main(argv: Optional[list[str]] = None) -> int:
    use_shipped_fastdds_profile()
    # rclpy's own handlers would shut the context down at once; ours let the node save its outputs first.
    rclpy.init(args=argv if argv is not None else sys.argv, signal_handler_options=SignalHandlerOptions.NO)
    stop = StopRequest()
    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    try:
        node = SlamNode()
    except (NodeParameterError, ConfigError) as error:
        rclpy.logging.get_logger("slam_node").fatal(f"invalid parameters: {error}")
        rclpy.try_shutdown()
        return EXIT_BAD_PARAMETERS
    executor = node_executor()
    executor.add_node(node)
    status = EXIT_INTERRUPTED
    try:
        while rclpy.ok() and not stop.requested and not node.failed:
            spin_once(executor, 0.1)
        node.get_logger().info("shutting down" + (": saving outputs" if node.settings.save_on_shutdown else ""))
        status = node.finish(save=node.settings.save_on_shutdown and not node.failed)
    except KeyboardInterrupt:
        node.get_logger().warning("interrupted again: outputs not saved")
        node.abort()
    finally:
        executor.shutdown(timeout_sec=0)
        node.destroy_node()
        rclpy.try_shutdown()
    return status


if __name__ == "__main__":
    sys.exit(main())
