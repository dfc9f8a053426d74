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

The node is glue: its ROS entities, lifecycle and callbacks, over its parts, none of which holds a ROS entity it
did not get from the node: the input pipeline (input_pipeline.py), the SLAM runtime's host (runtime_host.py), the
pose outputs (pose_output.py), the status (diagnostics.py), the mesh (mesh_publication.py), the parameters
(parameters.py, node_params.py), robot odometry and TF (robot_odometry.py, tf_chain.py).

Run: `ros2 run eslam_ros slam_node --ros-args --params-file config/slam_node.yaml -r rgb/image:=...` or, after a
pip install, `slam_node --ros-args ...` (see docs/ros.md).
"""
from __future__ import annotations

import signal
import sys
import time
import traceback
from typing import Any, Optional, Sequence

import numpy as np
import rclpy
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.executors import MultiThreadedExecutor
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import CameraInfo, Image
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from eslam_core.config import ConfigError
from eslam_core.cpu import freeze_start_up_objects
from eslam_core.runtime import RuntimeCrashed
from eslam_ros.diagnostics import InputMonitor, StatusInputs, StatusReport, health_values
from eslam_ros.input_pipeline import (DEPTH, RGB, STREAM_NAMES, AcceptedFrame, InputPipeline, PipelineEvent,
                                     SkippedInput, StreamRestart, configured_intrinsics)
from eslam_ros.mesh_publication import MESH_POLL_S, MeshPublication
from eslam_ros.node_params import NodeParameterError
from eslam_ros.node_threads import CallbackGate, LogThrottle, PeriodicThread, StopRequest, node_executor, spin_once
from eslam_ros.parameters import declare_node_parameters, read_parameters
from eslam_ros.pose_output import PoseOutput
from eslam_ros.qos import input_qos, latched_qos, use_shipped_fastdds_profile
from eslam_ros.robot_odometry import RobotOdometry
from eslam_ros.runtime_host import EXIT_FAILED, EXIT_OK, LIVE_DRAIN_TIMEOUT_S, RuntimeHost
from eslam_ros.tf_chain import TfOdometry, select_setup

EXIT_BAD_PARAMETERS, EXIT_INTERRUPTED = 2, 130
POSE_WAIT_S = 0.05  # the pose thread's longest wait for a pose (it checks for a stop request in between)


# ================================================================================================= input pipeline


# ================================================================================================= the node


def _refused(request: Any, response: Any) -> Any:
    response.success, response.message = False, "the node is shutting down or failed; see its log"
    return response


class SlamNode(LifecycleNode):
    """The ROS 2 node; see the module docstring for its topics, services and conventions.

    A managed node: configure / activate / deactivate / cleanup / shutdown are lifecycle transitions
    (`slam_lifecycle_node` waits for them; the plain `slam_node` makes the first two itself, `start_node`). Inputs
    and periodic outputs belong to "active"; publishers, services and the map live from configure to cleanup.
    Parameters may change while unconfigured (they are read at configure); afterwards changes are refused."""

    def __init__(self, node_name: str = "slam_node", **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        self.lifecycle_state = "unconfigured"
        self.parameters_open = True
        self.configured = False
        self.configure_error: Optional[str] = None
        self.host: Optional[RuntimeHost] = None  # the SLAM runtime's, from configure to cleanup
        self.exit_status = EXIT_OK
        declare_node_parameters(self)  # settable while unconfigured (`ros2 param set`), read at configure
        self.add_on_set_parameters_callback(self._refuse_parameter_changes)

    # ------------------------------------------------------------------------------------------ lifecycle

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self.configure_slam()
        except (NodeParameterError, ConfigError) as error:
            self.configure_error = str(error)
            self.get_logger().error(f"configure failed: invalid parameters: {error}")
            return TransitionCallbackReturn.FAILURE
        self.configured, self.parameters_open, self.configure_error = True, False, None
        self.lifecycle_state = "inactive"
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self.failed:
            self.get_logger().error(f"not activated: {self.failed}; clean up and configure again")
            return TransitionCallbackReturn.FAILURE
        self.activate_slam()
        self.lifecycle_state = "active"
        self.get_logger().info("active: taking input" + (" (the map so far goes on)" if self.runtime else ""))
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.deactivate_slam()
        self.lifecycle_state = "inactive"
        self.get_logger().info("inactive: tracking and mapping paused, map kept")
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.release()
        self.lifecycle_state, self.parameters_open = "unconfigured", True
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.release()
        self.lifecycle_state = "finalized"
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self.configured:
            self.abort()
            self.destroy_slam_entities()
            self.configured = False
        self.lifecycle_state, self.parameters_open = "unconfigured", True
        return TransitionCallbackReturn.SUCCESS

    def release(self) -> None:
        """Save (save_on_shutdown) and stop the runtime, then remove what configure made."""
        if not self.configured:
            return
        self.exit_status = self.finish(save=self.settings.save_on_shutdown and not self.failed)
        self.destroy_slam_entities()
        self.host = None
        self.configured = False

    @property
    def runtime(self) -> Any:
        return self.host.runtime if self.host is not None else None

    @property
    def failed(self) -> Optional[str]:
        """Why the SLAM runtime failed (the node then stops with an error), or None."""
        return self.host.failed if self.host is not None else None

    def configure_slam(self) -> None:
        """Read the parameters, make the input pipeline, the publishers and the services (no input yet)."""
        self.settings, self.config = read_parameters(self)
        s = self.settings
        self.tf_setup = select_setup(s)
        self.pipeline = InputPipeline(
            queue_size=s.sync_queue_size,
            max_interval=s.sync_max_interval or None,
            age_penalty=s.sync_age_penalty,
            depth_scale=s.depth_scale or None,
            fixed_intrinsics=configured_intrinsics(self.config),
            time_jump_reset=s.time_jump_reset or None,
        )
        self.active = False
        self.restarts = 0  # image streams that started over (their stamps jumped back)
        self.input_seconds = 0.0  # the node's own share of the work: pairing, conversion, hand-over
        self._throttle = LogThrottle(s.log_throttle)
        self.inputs = InputMonitor()
        self.camera_frame = ""  # the image frame_id (the camera optical frame), once known
        self._last_image = time.monotonic()

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
        self.mesh = MeshPublication(
            lambda data: self.mesh_pub.publish(data), s.map_frame, lambda: self.get_clock().now().to_msg(),
            self.get_logger(), resolution=self._mesh_resolution() or self.config.mesh.resolution,
            block_size=s.mesh_block_size, period=s.mesh_period, budget_s=s.mesh_time_budget,
            triangle_budget=s.mesh_triangle_budget, nice=s.mesh_nice, duty=s.mesh_duty)
        # A new subscriber gets every block of the mesh (messages carry only changes): see mesh_publication.py.
        self.mesh_pub = self.create_publisher(MarkerArray, "~/mesh", latched_qos(), event_callbacks=(
            PublisherEventCallbacks(matched=self.mesh.subscriber_matched)))
        # Above the camera: map "up" is z with REP 105 (map = odom), -y in camera mode (map = optical frame).
        self.status = StatusReport(self, s.diagnostics_hardware_id, s.map_frame, np.array(
            [0.0, 0.0, 0.4]) if self.tf_setup.rep105 else np.array([0.0, -0.4, 0.0]), s.no_input_timeout,
                                   s.min_input_rate)
        tf_odometry = TfOdometry(self, s.odom_frame, s.base_frame) if "tf" in (
            self.tf_setup.odometry, self.tf_setup.extrinsic) else None
        self.odometry: Optional[RobotOdometry[AcceptedFrame]] = RobotOdometry(
            s, self.tf_setup, tf_odometry) if self.tf_setup.rep105 else None
        self.poses = PoseOutput(self, s, self.tf_setup, self.odometry, self._throttle)
        self.host = RuntimeHost(s, self.config, self.get_logger(), self._throttle, self.poses)

        self._configured_entities: list = [self.create_timer(s.status_period, gate(self._publish_status),
                                                             callback_group=self._status)]
        savers = {"~/save_mesh": ("mesh.ply", lambda rt, p: rt.save_mesh(p, resolution=self._mesh_resolution())),
                  "~/save_trajectory": ("trajectory.txt", lambda rt, p: rt.save_trajectory(p)),
                  "~/save_checkpoint": ("checkpoint.pt", lambda rt, p: rt.save_checkpoint(p))}
        services = {name: (lambda request, response, saver=saver: _answer(response, *self.host.save(*saver)))
                    for name, saver in savers.items()}
        for name, handler in (*services.items(), ("~/reset", self._srv_reset), ("~/load_map", self._srv_load_map)):
            self._configured_entities.append(
                self.create_service(Trigger, name, gate(handler, when_closed=_refused), callback_group=self._slow))
        self._active_entities: list = []

        self.get_logger().info(f"TF: {self.tf_setup.describe(s)}")
        self.get_logger().info(
            f"ESLAM node ready: {'config file ' + s.config_file if s.config_file else 'preset ' + s.preset}, "
            f"{s.workers} worker(s), {s.policy} policy, tracking mode {self.config.tracking.mode}, input QoS "
            f"{s.input_qos}, poses in '{s.map_frame}', outputs to {self.host.output_dir.resolve()}; waiting for "
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
            _destroy(self, entity)
        self._active_entities = []
        self._stop_threads()
        if self.runtime is not None and not self.failed:
            self.host.drain(LIVE_DRAIN_TIMEOUT_S)

    def destroy_slam_entities(self) -> None:
        """Cleanup: every publisher, service and timer the node made (after `finish`)."""
        if self.active:
            self.deactivate_slam()
        for entity in self._configured_entities + self.poses.publishers + [
                self.mesh_pub] + self.status.publishers:
            _destroy(self, entity)
        self._configured_entities = []

    # ------------------------------------------------------------------------------------------ parameters

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
        self.input_seconds += time.monotonic() - start

    def _on_odometry(self, msg: Odometry) -> None:
        self.inputs.arrived("odom")
        refused = self.odometry.add_message(msg, time.monotonic())
        if refused and self._throttle.allow("odom_rejected"):
            self.get_logger().warning(f"{refused} [odom_rejected: {self.odometry.counts['odom_rejected']} so far]")

    def _accept(self, accepted: AcceptedFrame) -> None:
        """A frame from the pipeline: to the runtime, in REP 105 mode once its odometry is settled."""
        self.inputs.arrived("pair")
        self.camera_frame = accepted.frame_id
        if self.odometry is None:
            self.host.submit(accepted)
            return
        self.odometry.push(accepted.frame.timestamp, accepted.frame_id, accepted, time.monotonic())
        self._release_odometry()

    def _release_odometry(self, flush: bool = False) -> None:
        for frame in self.odometry.settled(time.monotonic(), flush, self.config.tracking.mode == "external",
                                           self._warn_odometry):
            self.host.submit(frame)

    def _warn_odometry(self, kind: str, message: str) -> None:
        if self._throttle.allow(f"odom_{kind}"):
            self.get_logger().warning(f"{message} [{self.odometry.counts}]")

    def _tick_inputs(self) -> None:
        """Frames held while the runtime started go to it once it runs; after `sync_idle_flush` s without an image
        the stream ended (or paused), so the pending pair will not get a better match."""
        if self.runtime is not None:
            self.host.submit_held()
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
                self.restarts += 1
                self.get_logger().warning(f"image stamps jumped back by {event.jump:.3f} s (a bag started over?): "
                                          f"resetting the map")
                self._reset_runtime()

    # ------------------------------------------------------------------------------------------ outputs

    def _pose_out(self) -> None:
        if self.runtime is None or self.failed or self.gate.closed:
            time.sleep(POSE_WAIT_S)
            return
        try:
            self.host.publish_poses(wait=POSE_WAIT_S)
        except Exception as error:  # noqa: BLE001 - reported, and the node goes on (or stops, if SLAM died)
            self._on_callback_error(error)

    def _stop_threads(self) -> None:
        """After this, poses are published by the caller (`_drain`) only, so they stay in order."""
        for thread in getattr(self, "_threads", []):
            thread.stop()
        self._threads = []

    def _publish_path(self) -> None:
        if self.runtime is not None and not self.failed:
            self.poses.publish_path(self.runtime, self.camera_frame)

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
        return self.host.state()

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
        held = self.host.held
        return self.runtime is not None or held.has_room(held.bytes // max(len(held), 1))

    def health(self) -> dict[str, Any]:
        """The runtime's health figures and the node's counters, as published on ~/status."""
        return health_values(self)

    def _publish_status(self) -> None:
        now = time.monotonic()
        values = self.health()
        self.status.publish(values, StatusInputs(
            failed=self.failed, state=values["runtime"], poses=self.poses.counts.poses,
            silent_s={name: self.inputs.silent_for(name, now) for name in self.watched_inputs()} if self.active
            else {}, pair_rate_hz=values["input_rate_hz"], measured_for_s=now - self.inputs.started,
            lost=f"quality {values.get('tracking_quality', 0.0):.2f}" if self.poses.lost else None,
            degraded=self.poses.degraded,
            map_disagreement_cm=values.get("map_disagreement_cm") if values.get("map_disagrees") else None),
            self.odometry is not None, self.poses.last_position,
            self.get_clock().now().to_msg(), now)

    def watched_inputs(self) -> list[str]:
        """Inputs whose silence is a warning: the images, and the odometry topic when there is one."""
        return list(STREAM_NAMES) + (["odom"] if self.tf_setup.odometry == "topic" else [])

    # ------------------------------------------------------------------------------------------ services

    def _srv_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self.runtime is None:
            return _answer(response, False, "nothing to reset: no frame received yet")
        self._reset_runtime()
        return _answer(response, True, "map and trajectory cleared; the next frame starts a new map")

    def _srv_load_map(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Continue in the map of `map_file` (RuntimeHost.load_map), checked against the session's camera."""
        loaded, message = self.host.load_map(self.pipeline.intrinsics)  # (None before the first frame)
        if loaded:
            self.mesh.reset()
            self.get_logger().info(f"~/load_map: {message}")
        else:
            self.get_logger().warning(f"~/load_map refused: {message}")
        return _answer(response, loaded, message)

    def _reset_runtime(self) -> None:
        self.host.reset()
        self.mesh.reset()
        if self.odometry is not None:
            self.odometry.reset()

    # ------------------------------------------------------------------------------------------ end of the run

    def _on_callback_error(self, error: BaseException) -> None:
        if isinstance(error, RuntimeCrashed):
            self.host.fail(f"the SLAM runtime crashed: {error}")
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
        if self.host.started() is not None and not self.failed:
            self._handle(self.pipeline.flush())
            if self.odometry is not None:
                self._release_odometry(flush=True)
        return self.host.finish(save, self._mesh_resolution())

    def abort(self) -> None:
        """Stop the runtime at once, saving nothing (a second Ctrl-C)."""
        self._stop_threads()
        self.mesh.close()
        self.host.abort()


def _destroy(node: Node, entity: Any) -> None:
    kind = type(entity).__name__
    destroy = {"Subscription": node.destroy_subscription, "Timer": node.destroy_timer,
               "Service": node.destroy_service}.get(kind, node.destroy_publisher)
    destroy(entity)


def _answer(response: Trigger.Response, success: bool, message: str) -> Trigger.Response:
    response.success, response.message = success, message
    return response


# ================================================================================================= process


def start_node(node_name: str = "slam_node", **node_kwargs: Any) -> SlamNode:
    """A node configured and activated through its lifecycle transitions, as the plain `slam_node` runs (so that
    `ros2 lifecycle get` says active); raises NodeParameterError with the reason where configure fails."""
    node = SlamNode(node_name, **node_kwargs)
    if node.trigger_configure() != TransitionCallbackReturn.SUCCESS:
        reason = node.configure_error or "configure failed; see the log"
        node.destroy_node()
        raise NodeParameterError(reason)
    node.trigger_activate()
    return node


def main(argv: Optional[list[str]] = None, managed: bool = False) -> int:
    """`slam_node` (configured and activated at once) or, `managed`, `slam_lifecycle_node` (waits for the
    transitions). Runs until a stop signal, a failure or the shutdown transition; saves as cleanup does."""
    use_shipped_fastdds_profile()
    # rclpy's own handlers would shut the context down at once; ours let the node save its outputs first.
    rclpy.init(args=argv if argv is not None else sys.argv, signal_handler_options=SignalHandlerOptions.NO)
    stop = StopRequest()
    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    try:
        node = SlamNode() if managed else start_node()
    except NodeParameterError as error:
        rclpy.logging.get_logger("slam_node").fatal(f"invalid parameters: {error}")
        rclpy.try_shutdown()
        return EXIT_BAD_PARAMETERS
    # (The managed node's transitions run on the executor's threads: rclpy issue 1142, see spin_once.)
    executor = MultiThreadedExecutor(num_threads=2) if managed else node_executor()
    executor.add_node(node)
    freeze_start_up_objects()  # (a full collection of them stalled every callback: cpu.py)
    status = EXIT_INTERRUPTED
    try:
        while rclpy.ok() and not stop.requested and not node.failed and node.lifecycle_state != "finalized":
            spin_once(executor, 0.1)
        if node.configured:
            node.get_logger().info("shutting down" + (": saving outputs" if node.settings.save_on_shutdown else ""))
            node.release()
        status = EXIT_FAILED if node.failed else node.exit_status
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
