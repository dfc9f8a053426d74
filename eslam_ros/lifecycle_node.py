"""The managed (lifecycle) variant of the SLAM node: `slam_lifecycle_node`, or `python -m eslam_ros.lifecycle_node`.

The same node as `slam_node` (topics, services, parameters), driven by the ROS 2 lifecycle state machine
(`ros2 lifecycle set /slam_node configure`, or nav2's lifecycle_manager):

    unconfigured --configure--> inactive --activate--> active
      configure   reads and checks the parameters (a bad one fails the transition and says why), makes the input
                  pipeline, publishers and services; ~/status and /diagnostics start (state "inactive")
      activate    subscribes to the inputs and starts poses, path and mesh; the SLAM runtime starts with the first
                  frame (it needs the camera), and a map kept from before goes on
      deactivate  unsubscribes and stops the periodic outputs after the frames already submitted are tracked: tracking
                  and mapping pause, the map and trajectory stay (services still save them)
      cleanup     saves trajectory, checkpoint and mesh as a shutdown of slam_node does (save_on_shutdown), stops
                  the runtime and removes everything configure made; back to unconfigured
      shutdown    the same saving from any state, then finalized (the process exits)
Parameters may be changed while unconfigured (they are read at configure); afterwards changes are refused.
Ctrl-C / SIGTERM saves and exits as slam_node does.
"""
from __future__ import annotations

import signal
import sys
from typing import Any, Optional

import rclpy
from rclpy.executors import MultiThreadedExecutor
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.signals import SignalHandlerOptions

from eslam_core.config import ConfigError
from eslam_ros.node_params import NodeParameterError
from eslam_ros.qos import use_shipped_fastdds_profile
from eslam_ros.node_threads import StopRequest, spin_once
from eslam_ros.slam_node import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, SlamNode


class LifecycleSlamNode(SlamNode, LifecycleNode):
    """SlamNode whose configure / activate / deactivate / cleanup / shutdown are lifecycle transitions."""

    def __init__(self, node_name: str = "slam_node", **node_kwargs: Any) -> None:
        LifecycleNode.__init__(self, node_name, **node_kwargs)  # not SlamNode.__init__: nothing starts yet
        self.lifecycle_state = "unconfigured"
        self.parameters_open = True
        self.configured = False
        self.runtime = None
        self.failed: Optional[str] = None
        self.exit_status = EXIT_OK
        self.declare_node_parameters()  # settable while unconfigured (`ros2 param set`), read at configure
        self.add_on_set_parameters_callback(self._refuse_parameter_changes)
        self._refusing_parameter_changes = True

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self.configure_slam()
        except (NodeParameterError, ConfigError) as error:
            self.get_logger().error(f"configure failed: invalid parameters: {error}")
            return TransitionCallbackReturn.FAILURE
        self.configured, self.parameters_open = True, False
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
        self.runtime = None
        self.configured = False


def main(argv: Optional[list[str]] = None) -> int:
    use_shipped_fastdds_profile()
    rclpy.init(args=argv if argv is not None else sys.argv, signal_handler_options=SignalHandlerOptions.NO)
    stop = StopRequest()
    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    node = LifecycleSlamNode()
    executor = MultiThreadedExecutor(num_threads=2)
    executor.add_node(node)
    status = EXIT_INTERRUPTED
    try:
        while rclpy.ok() and not stop.requested and not node.failed and node.lifecycle_state != "finalized":
            spin_once(executor, 0.1)
        if node.lifecycle_state == "finalized":
            status = node.exit_status
        elif node.configured:
            node.get_logger().info("shutting down" + (": saving outputs" if node.settings.save_on_shutdown else ""))
            node.release()
            status = node.exit_status
        else:
            status = EXIT_FAILED if node.failed else EXIT_OK
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
