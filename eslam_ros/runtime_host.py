"""The node's SLAM runtime, from its first frame to its last: what the node drives, holding no ROS entity.

The runtime needs the camera, so it starts with the first accepted frame, on a thread of its own (spawning workers
takes seconds, and the input callbacks must keep taking messages meanwhile). Frames accepted while it starts wait
in the start-up queue (offline: all of them, up to start_queue_bytes; live: the newest 30). Every frame goes to the
runtime with its tag, which its pose update brings back to the pose output. A reset starts a new map; a loaded map
replaces the runtime (the next frame starts the new one); a crash is kept as `failed`, and the node stops on it.
"""
from __future__ import annotations

import dataclasses
import math
import threading
import time
from pathlib import Path
from typing import Any, Callable, Optional

from eslam_core.atomic import failure_line, make_output_folder
from eslam_core.camera import Intrinsics
from eslam_core.config import Config
from eslam_core.runtime import RuntimeCrashed, make_runtime
from eslam_core.slam import read_loadable
from eslam_ros.input_pipeline import AcceptedFrame
from eslam_ros.node_params import NodeSettings
from eslam_ros.node_threads import LogThrottle
from eslam_ros.pose_output import FrameTag, PoseOutput
from eslam_ros.start_queue import StartQueue, frame_bytes

EXIT_OK, EXIT_FAILED = 0, 1
# At shutdown with the live policy: how long the frame in progress may take before the runtime is stopped.
LIVE_DRAIN_TIMEOUT_S = 10.0


class RuntimeHost:
    def __init__(self, settings: NodeSettings, config: Config, logger: Any, throttle: LogThrottle,
                 poses: PoseOutput) -> None:
        self.settings, self.config, self.log, self.throttle, self.poses = settings, config, logger, throttle, poses
        self.output_dir = Path(settings.output_dir).expanduser()
        self.runtime = None
        self.failed: Optional[str] = None  # why the runtime failed: the node then stops with an error
        self.dropped_while_starting = 0
        self.held: StartQueue[AcceptedFrame] = StartQueue(settings.policy, settings.start_queue_bytes)
        self._starter: Optional[threading.Thread] = None
        self._load_map = bool(settings.map_file)  # the next runtime starts from map_file
        self._lock = threading.Lock()  # the runtime's replacement (reset, load_map) against the input thread

    def state(self) -> str:
        """waiting (for a first frame), starting, running or failed."""
        if self.failed:
            return "failed"
        return "running" if self.runtime else "starting" if self._starter else "waiting"

    def fail(self, message: str) -> None:
        if self.failed is None:
            self.log.fatal(message)
        self.failed = message

    # ---------------------------------------------------------------------------------------------- frames in
    def submit(self, accepted: AcceptedFrame) -> None:
        if self.failed:
            return
        if self.runtime is None:
            if self._starter is None:
                self._starter = threading.Thread(target=self._start, args=(accepted.intrinsics,),
                                                 name="eslam-runtime-start", daemon=True)
                self._starter.start()
            dropped = self.held.push(accepted, frame_bytes(accepted.frame))
            if dropped:
                self.dropped_while_starting += dropped
                if self.throttle.allow("dropped_while_starting"):
                    self.log.warning(
                        f"{self.dropped_while_starting} frame(s) dropped while the SLAM runtime starts: "
                        + (f"more than start_queue_bytes = {self.settings.start_queue_bytes} bytes queued; raise it"
                           if self.settings.policy == "offline" else "the live policy keeps the newest 30"))
            return
        self.submit_held()
        self._submit_now(accepted)

    def submit_held(self) -> None:
        while self.held and self.runtime is not None and not self.failed:
            self._submit_now(self.held.popleft())

    def _submit_now(self, accepted: AcceptedFrame) -> None:
        tag = FrameTag(accepted.stamp, accepted.frame_id, accepted.received, accepted.odometry)
        try:
            self.runtime.submit(dataclasses.replace(accepted.frame, tag=tag))
        except RuntimeCrashed as error:
            self.fail(f"the SLAM runtime crashed: {error}")

    def _start(self, intrinsics: Intrinsics) -> None:
        """Runs on the starter thread; the pipeline has fixed the intrinsics to these."""
        s = self.settings
        self.log.info(f"starting the SLAM runtime ({s.workers} worker(s), {s.policy}) for {intrinsics}")
        checkpoint = s.map_file if self._load_map else None
        self._load_map = False
        try:
            runtime = make_runtime(self.config, intrinsics, workers=s.workers, policy=s.policy, checkpoint=checkpoint)
            runtime.start()
        except (RuntimeCrashed, ValueError) as error:
            self.fail(f"the SLAM runtime did not start: {error}")
            return
        self.runtime = runtime
        self.log.info("SLAM runtime running")

    # ---------------------------------------------------------------------------------------------- poses out
    def publish_poses(self, wait: float = 0.0) -> None:
        if self.runtime is None or self.failed:
            return
        try:
            updates = self.runtime.poll(timeout=wait)
        except RuntimeCrashed as error:
            self.fail(f"the SLAM runtime crashed: {error}")
            return
        self.poses.publish(updates)

    def drain(self, timeout: float) -> None:
        """Publish poses until every submitted frame got one (or was dropped), or `timeout` seconds passed."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not self.failed:
            self.publish_poses()
            health = self.runtime.health()
            if health.frames_tracked + health.frames_dropped >= health.frames_received:
                self.publish_poses()
                return
            time.sleep(0.02)

    # ---------------------------------------------------------------------------------------------- the map
    def reset(self) -> None:
        """A new map from the next frame; poses of frames submitted before are not published."""
        with self._lock:
            if self.runtime is not None:
                self.runtime.reset()
            self.poses.reset()

    def load_map(self, camera: Optional[Intrinsics]) -> tuple[bool, str]:
        """Drop the current map and continue in the one of `map_file` (from the next frame, relocalized), once the
        file passed every check its load makes (slam.read_loadable: intact, this version, this configuration's
        model settings and image scale, and the session's `camera` once a frame gave it); a file that fails one is
        refused with that line and the current map goes on, untouched. (success, message)."""
        path = self.settings.map_file
        if not path:
            return False, "no map_file parameter set: start the node with map_file:=<checkpoint.pt> (parameters are " \
                          "read at start-up)"
        try:
            read_loadable(path, self.config, camera)
        except ValueError as error:  # CheckpointError, one line: what is wrong and what to do
            kept = "the current map goes on" if self.runtime is not None else "nothing changed"
            return False, f"{error} (map not loaded, {kept})"
        with self._lock:
            old, self.runtime = self.runtime, None
            if self._starter is not None:
                self._starter.join()
                old, self.runtime = old or self.runtime, None
            self._starter, self._load_map = None, True
            self.poses.reset()
        if old is not None:
            old.close(drain=False)
        return True, f"{path}: the next frame starts in this map" + (
            "" if camera is not None else " (its camera is checked against the first frame's: none received yet)")

    def save(self, name: str, save: Callable[[Any, Path], Any]) -> tuple[bool, str]:
        """`save(runtime, path)` into the output folder: (success, the path or one line saying what failed)."""
        if self.runtime is None or self.failed:
            return False, self.failed or "nothing to save yet: no frame has been received"
        path = self.output_dir / name
        try:
            make_output_folder(path.parent)
            save(self.runtime, path)
        except (ValueError, OSError, RuntimeCrashed) as error:
            # One line (a full disk: the space needed and what to do); an older file of that name is intact.
            line = failure_line(path, error)
            self.log.error(line)
            return False, line
        self.log.info(f"wrote {path}")
        return True, str(path.resolve())

    # ---------------------------------------------------------------------------------------------- the end
    def started(self) -> Optional[Any]:
        """The runtime once its start is over (the runtime bounds its own start-up time); None if it never ran."""
        if self._starter is not None:
            self._starter.join()
        return self.runtime

    def finish(self, save: bool, mesh_resolution: Optional[float]) -> int:
        """Hand over the frames still held, publish the last poses (offline: of every submitted frame; live: of the
        frame in progress), stop the runtime and save trajectory, checkpoint and mesh from its final state. The
        process exit status."""
        runtime = self.started()
        if runtime is None:
            return EXIT_FAILED if self.failed else EXIT_OK
        try:
            if not self.failed:
                self.submit_held()
                self.drain(math.inf if self.settings.policy == "offline" else LIVE_DRAIN_TIMEOUT_S)
            runtime.close(timeout=LIVE_DRAIN_TIMEOUT_S)
        except RuntimeCrashed as error:
            self.fail(f"the SLAM runtime crashed: {error}")
            return EXIT_FAILED
        if save and not self.failed:
            # Small and most valuable first: on a disk that fills up, the trajectory is what still gets written;
            # each failure is one line and does not stop the next output.
            for name, save_one in (("trajectory.txt", lambda rt, p: rt.save_trajectory(p)),
                                   ("checkpoint.pt", lambda rt, p: rt.save_checkpoint(p)),
                                   ("mesh.ply", lambda rt, p: rt.save_mesh(p, resolution=mesh_resolution))):
                self.save(name, save_one)
        return EXIT_FAILED if self.failed else EXIT_OK

    def abort(self) -> None:
        """Stop the runtime at once, saving nothing (a second Ctrl-C)."""
        if self.runtime is not None:
            try:
                self.runtime.close(timeout=0, drain=False)
            except RuntimeCrashed:
                pass
