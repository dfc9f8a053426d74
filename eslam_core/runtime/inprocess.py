"""The single-process runtime: the lock-step `SLAM` on a background thread, behind the runtime API.

Frames wait in a bounded queue (offline: `submit` blocks while it is full; live: the oldest pending frame makes
room, and the SLAM thread takes the oldest waiting frame while at most `runtime.live_backlog` more wait behind
it, else skips to the newest: api.frames_to_skip). The SLAM thread tracks each frame
and, every `mapping.every` frames, maps, exactly as `eslam run --workers 1` does. A copy of the trajectory is kept
up to date after every step, so `trajectory()` never waits for the step in progress; checkpoints and meshes are
made from a copy of the SLAM state taken between two steps.

"Stop now" (`close(drain=False)`, `reset()`) abandons the mapping step in progress after its current iteration
(`SLAM.after_mapping_iteration`), so that a long warm-up does not hold up a shutdown. torch's thread count is
process-wide: `threads` (or `run.threads`) sets it for the whole process.
"""
from __future__ import annotations

import logging
import math
import threading
import time
import traceback
from collections import deque
from typing import Optional

import numpy as np
import torch

from eslam_core.camera import Frame, Intrinsics
from eslam_core.config import Config
from eslam_core.slam import SLAM, loaded_slam
from eslam_core.trajectory import TrackedTrajectory
from eslam_core.runtime.saving import SavingMixin
from eslam_core.runtime.mesher import snapshot_for_meshing
from eslam_core.runtime.api import Health, PoseUpdate, RuntimeCrashed, RuntimeSetupError, check_frame, check_policy, \
    frames_to_skip, peak_rss_mb
from eslam_core.runtime.parent_state import ParentState

log = logging.getLogger("eslam")


class _StepInterrupted(Exception):
    """Raised after a mapping iteration of the SLAM thread when the caller asked to stop now or to reset."""


class InProcessRuntime(SavingMixin):
    def __init__(self, cfg: Config, intrinsics: Intrinsics, policy: str = "offline", threads: Optional[int] = None,
                 checkpoint: Optional[str] = None):
        self.cfg = cfg
        self.checkpoint = checkpoint  # a saved map to start from (see loaded_slam); a reset starts an empty one
        self.intrinsics = intrinsics
        self.policy = check_policy(policy)
        self.threads = threads or cfg.run.threads or None
        self.capacity = cfg.runtime.capacity  # (checked with the config)
        self._cond = threading.Condition()  # guards the input queue, the flags below and the counts
        self._inputs: deque = deque()
        self._closing = self._stop_now = False
        self._slam_lock = threading.Lock()  # held for a whole step: the SLAM object is consistent between steps
        self._lock = threading.Lock()  # guards what the caller reads: the parent state
        self._posed = threading.Condition(self._lock)  # a new pose update (or a crash)
        self._started = self._closed = False
        self._crash: Optional[RuntimeCrashed] = None
        self._thread: Optional[threading.Thread] = None
        self._epoch = 0
        self._step_epoch = 0  # the epoch of the step in progress
        # Since start (over resets); the map changes with every mapping step and every loop closed.
        self._counts = dict(received=0, tracked=0, dropped=0, map_changes=0)
        self._new_map()

    def _new_map(self) -> None:
        self.slam = loaded_slam(self.checkpoint, self.cfg, self.intrinsics) if self.checkpoint else \
            SLAM(self.cfg, self.intrinsics)
        self.slam.after_mapping_iteration = self._after_iteration
        self.checkpoint = None
        # what the caller reads while a step runs
        self._parent = ParentState(TrackedTrajectory.from_state_dict(self.slam.trajectory.state_dict()))
        self._memory = {"map_bytes": 0, "keyframe_bytes": 0, "keyframes_kept": 0}

    # ------------------------------------------------------------------------------------------------ the API
    def start(self) -> None:
        if self._started:
            raise RuntimeSetupError("the runtime is already started (start() is called once; use reset() to begin "
                                    "a new map)")
        self._started = True
        if self.threads:
            torch.set_num_threads(self.threads)
        self._thread = threading.Thread(target=self._run, name="eslam-slam", daemon=True)
        self._thread.start()

    def _check_running(self) -> None:
        if not self._started:
            raise RuntimeSetupError("the runtime is not started: call start() first (or use it in a `with` block)")
        if self._closed:
            raise RuntimeSetupError("the runtime is closed: make a new one with make_runtime()")
        if self._crash is not None:
            raise self._crash

    def submit(self, frame: Frame) -> None:
        self._check_running()
        check_frame(frame, self.intrinsics)
        with self._lock:
            self._parent.submitted(frame.index, frame.tag)
        item = (frame, time.monotonic(), self._epoch)
        with self._cond:
            self._counts["received"] += 1
            while len(self._inputs) >= self.capacity:
                if self.policy == "live":
                    self._inputs.popleft()
                    self._counts["dropped"] += 1
                    break
                self._cond.wait(0.1)
                if self._crash is not None:
                    raise self._crash
                if self._stop_now:  # close(drain=False) from another thread: nobody will take it
                    self._counts["dropped"] += 1
                    return
            self._inputs.append(item)
            self._cond.notify_all()

    def poll(self, timeout: float = 0.0) -> list[PoseUpdate]:
        if self._crash is not None and not self._closed:
            raise self._crash
        with self._posed:
            if timeout > 0 and not self._parent.updates and self._started and not self._closed:
                self._posed.wait(timeout)
                if self._crash is not None:
                    raise self._crash
            return self._parent.take_updates()

    def trajectory(self, max_poses: Optional[int] = None) -> tuple[np.ndarray, np.ndarray]:
        if self._closed:
            return self.slam.trajectory.timestamps(max_poses), self.slam.trajectory.poses(max_poses)
        with self._lock:
            return self._parent.trajectory.timestamps(max_poses), self._parent.trajectory.poses(max_poses)

    def health(self) -> Health:
        with self._cond:
            pending, c = len(self._inputs), dict(self._counts)
        with self._lock:
            check = self.slam.tracking.map_check  # (replaced whole by the SLAM thread, never changed in place)
            return Health(frames_received=c["received"], frames_tracked=c["tracked"], frames_dropped=c["dropped"],
                          input_queue_depth=pending, keyframe_queue_depth=0, map_version=c["map_changes"],
                          **self._parent.health_figures(), **self._memory, peak_memory_mb={"process": peak_rss_mb()},
                          map_disagreement_cm=math.nan if check is None else 100.0 * check.metres,
                          map_disagrees=check is not None and check.disagrees)

    def _measure_map(self, epoch: int) -> None:
        """The map's memory and keyframe consistency for the health (computed outside the caller's lock)."""
        with self._slam_lock:
            if epoch != self._epoch:
                return
            memory = self.slam.atlas.memory()  # (summed over the submaps)
            consistency = self.slam.map.consistency() if self.slam.map.consistency_due() else None
        figures = {k: memory[k] for k in ("map_bytes", "keyframe_bytes", "keyframes_kept", "submaps", "loops_closed")}
        if self.slam.atlas.closures:
            figures["loop_correction_s"] = self.slam.atlas.closures[-1].seconds
        if consistency is not None:
            figures.update(consistency_mm=consistency.median_mm, consistency_agree=consistency.agree_fraction)
        with self._lock:
            if epoch == self._epoch:
                self._memory = {**self._memory, **figures}

    def snapshot(self) -> SLAM:
        """A copy of the SLAM state between two steps (after close(), the final state itself)."""
        if self._closed or not self._started:
            return self.slam
        with self._slam_lock:
            # Tensors are shared with the live state, which replaces (never modifies) them; the field is copied.
            return SLAM.from_state_dict(self.slam.state_dict())

    def mesh_snapshot(self, have: set):
        with self._slam_lock:  # (held for a whole step: the map between two steps)
            return snapshot_for_meshing(self.slam.atlas, have)

    def reset(self) -> None:
        self._check_running()
        with self._cond:
            self._counts["dropped"] += len(self._inputs)
            self._inputs.clear()
            self._epoch += 1  # also interrupts the step in progress
        with self._slam_lock, self._lock:
            self._new_map()

    def close(self, timeout: float | None = None, drain: Optional[bool] = None) -> None:
        """Finish (offline: every submitted frame; `drain=False`: stop now), stop the thread. Idempotent.
        `timeout`: seconds to wait for the work before stopping now anyway. Raises RuntimeCrashed if SLAM failed."""
        if self._closed:
            return
        self._closed = True
        if not self._started:
            return
        drain = self.policy == "offline" if drain is None else drain
        with self._cond:
            self._closing = True
            if not drain:
                self._stop_now_locked()
            self._cond.notify_all()
        self._thread.join(timeout if drain else None)
        if self._thread.is_alive():
            log.warning("runtime: the work did not finish within %.0f s; stopping now", timeout)
            with self._cond:
                self._stop_now_locked()
                self._cond.notify_all()
            self._thread.join()
        self.slam.after_mapping_iteration = None  # the final state, handed out by snapshot(), is the caller's now
        if self._crash is not None:
            raise self._crash

    def _stop_now_locked(self) -> None:
        self._stop_now = True
        self._counts["dropped"] += len(self._inputs)
        self._inputs.clear()

    def __enter__(self) -> "InProcessRuntime":
        if not self._started:
            self.start()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            self.close(drain=None if exc_type is None else False)
        except RuntimeCrashed:
            if exc_type is None:
                raise

    # ------------------------------------------------------------------------------------------ the SLAM thread
    def _next(self):
        with self._cond:
            while not self._inputs and not self._closing:
                self._cond.wait()
            if self._stop_now or not self._inputs:
                return None
            skip = frames_to_skip(len(self._inputs), self.policy == "live", self.cfg.runtime.live_backlog)
            self._counts["dropped"] += skip
            for _ in range(skip):
                self._inputs.popleft()
            item = self._inputs.popleft()
            self._cond.notify_all()
            return item

    def _run(self) -> None:
        try:
            while (item := self._next()) is not None:
                frame, arrival, epoch = item
                try:
                    with self._slam_lock:
                        if epoch != self._epoch:
                            raise _StepInterrupted  # submitted before a reset
                        self._step_epoch = epoch
                        res = self.slam.step(frame)
                        record = self.slam.trajectory.records[-1]
                except _StepInterrupted:
                    with self._cond:
                        self._counts["dropped"] += 1  # taken, never tracked
                    continue
                done = time.monotonic()
                with self._lock:
                    if epoch == self._epoch:  # else a reset came in after the step: it belongs to the old map
                        self._parent.posed(record, res.anchor, res.keyframe, done - arrival, done)
                        if res.keyframe:
                            self._parent.mapped(res.refined, done)
                        elif res.refined:  # a loop closed on a frame without a keyframe (submaps)
                            self._parent.corrected(res.refined)
                        self._posed.notify_all()
                if res.keyframe:  # after the pose is out: the consistency score takes tens of ms
                    self._measure_map(epoch)
                with self._cond:
                    self._counts["tracked"] += 1
                    self._counts["map_changes"] += int(res.keyframe or bool(res.refined))
        except BaseException as e:  # noqa: BLE001 - reported to the caller as a crash
            self._crash = RuntimeCrashed("slam", f"the SLAM thread failed: {type(e).__name__}: {e}",
                                         traceback.format_exc())
            log.error("%s\n%s", self._crash.summary, self._crash.traceback)
            with self._cond:
                self._cond.notify_all()
            with self._posed:
                self._posed.notify_all()

    def _after_iteration(self, iterations: int) -> bool:
        if self._stop_now or self._step_epoch != self._epoch:
            raise _StepInterrupted
        return False
