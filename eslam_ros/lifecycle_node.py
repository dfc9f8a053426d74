"""The managed start of the SLAM node: `slam_lifecycle_node`, or `python -m eslam_ros.lifecycle_node`.

The same node as `slam_node` (one class, `slam_node.SlamNode`: topics, services, parameters), left unconfigured for
the ROS 2 lifecycle state machine to drive (`ros2 lifecycle set /slam_node configure`, or nav2's
lifecycle_manager):

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

import sys
from typing import Optional

from eslam_ros import slam_node


def main(argv: Optional[list[str]] = None) -> int:
    return slam_node.main(argv, managed=True)


if __name__ == "__main__":
    sys.exit(main())
