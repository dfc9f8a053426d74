"""The pipelined runtime: a tracking process and a mapping process, driven from the caller's process (the parent).

    parent --frame ring (shared memory)--> tracker --keyframes--> mapper
       ^                                     ^  <---- map (shared memory, double buffered) ----|
       |                                     +<---- refined keyframe poses ---------------------|
       +<-- tracked poses, mapping reports, snapshots ------------------------------------------+

The parent prepares each submitted frame (resize, depth cut), writes it into the frame ring and returns; the
tracker tracks it against the newest map and sends the pose back; the mapper maps keyframes while the tracker goes
on. The parent keeps a mirror of the trajectory (each frame relative to its keyframe, keyframe poses updated with
the mapper's refinements), so `trajectory()` costs no round trip. Checkpoints and meshes are made from a snapshot:
the mapper sends its map and keyframes, the parent adds the trajectory and assembles a `SLAM` (the same object the
lock-step runtime has), so `load_checkpoint`, `eslam mesh` and `--resume` work on the result.

Workers are spawned (never forked: rclpy may live in this process) from a monitor thread that then watches their
sentinels and error pipes. A worker that dies is reported within a fraction of a second: its traceback is logged,
the other worker is stopped, and the next call to `submit`, `poll`, `close`, ... raises `RuntimeCrashed`. The
workers are started from that long-lived thread because the parent-death signal fires when the thread that
started a child ends, and the caller's thread may be short-lived.

`close()` (offline policy) lets the tracker finish every submitted frame and the mapper map every keyframe, takes
the final snapshot, then stops the workers and releases the shared memory. `close(drain=False)` (the default of the
live policy, and what Ctrl-C / SIGTERM use in `eslam run`) drops pending frames and abandons the current mapping
step instead, so it returns within about one optimiser iteration.
"""
from __future__ import annotations

import gc
import glob
import io
import itertools
import logging
import math
import multiprocessing.connection
import multiprocessing.synchronize
import os
import queue
import shutil
import signal
import tempfile
import threading
import time
import traceback
from contextlib import contextmanager
from typing import Callable, Optional

import numpy as np
import torch
import torch.multiprocessing as tmp

from eslam_core.camera import Frame, Intrinsics
from eslam_core.child_process import EXIT_ORPHANED, spawned_with_stop_signals_blocked
from eslam_core.config import Config
from eslam_core.frames import working_images, working_intrinsics
from eslam_core.slam import SLAM, loaded_trajectory
from eslam_core.submaps.atlas import Atlas
from eslam_core.trajectory import TrackedTrajectory
from eslam_core.runtime.saving import SavingMixin
from eslam_core.outputs.mesh import EmptyMeshError
from eslam_core.runtime.mesher import snapshot_for_meshing
from eslam_core.runtime.api import Health, PoseUpdate, RuntimeCrashed, RuntimeSetupError, \
    check_frame, check_policy, peak_rss_mb
from eslam_core.runtime.parent_state import ParentState
from eslam_core.runtime.shared import Control, Counter, FrameRing, HealthBoard, MapMeta, stage_profile
from eslam_core.runtime.workers import Channels, LoopClosed, MapperFinished, MapperSnapshot, MappingReport, \
    MeshRequest, SnapshotRequest, TrackedFrame, TrackerFinished, WorkerReady, WorkerSetup, mapper_main, tracker_main

log = logging.getLogger("eslam")

START_TIMEOUT_S = 180.0  # spawning imports torch in each worker: seconds on a loaded machine
SNAPSHOT_TIMEOUT_S = 120.0  # the mapper answers between two optimiser iterations (seconds at most)
STOP_GRACE_S = 30.0  # after "stop now": one tracking frame plus one optimiser iteration
JOIN_S = 5.0
HANG_S = 300.0  # a worker without a sign of life for this long (no loop pass, no optimiser iteration) is hung
MONITOR_S = 1.0  # how often the monitor looks at the heartbeats
WORKERS = ("tracker", "mapper")


# The workers' OpenMP threads sleep while they wait instead of spinning. Measured here with another process busy on
# one of the 2 cores: 10 mapping iterations took 16.2 s with 2 spinning threads, 5.6 s with 2 sleeping ones and
# 4.4 s with 1 thread. Lent threads (workers.CoreShare) always compete with the other worker now and then.
# A value the user set in the environment wins.
WORKER_ENV = {"OMP_WAIT_POLICY": "PASSIVE"}


@contextmanager
def worker_environment(defaults: dict):
    """Environment variables for the processes spawned inside the block (they read their environment at exec;
    OpenMP reads its settings when torch loads, before any worker code runs), restored afterwards."""
    added = {k: v for k, v in defaults.items() if k not in os.environ}
    os.environ.update(added)
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)


def default_threads() -> int:
    """Torch threads per worker: the cores this process may use, split between tracker and mapper."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count() or 2
    return max(1, cores // 2)


def semaphore_names(*objects) -> list[str]:
    """Names of the POSIX semaphores behind multiprocessing locks, conditions and queues (a diagnostic: they are
    the only named shared-memory objects the runtime creates, as /dev/shm/sem.<name>)."""
    names = []
    for obj in objects:
        members = [obj] if isinstance(obj, multiprocessing.synchronize.SemLock) else list(vars(obj).values())
        for m in members:
            if isinstance(m, multiprocessing.synchronize.Condition):
                names += semaphore_names(m)
            elif isinstance(m, multiprocessing.synchronize.SemLock) and m._semlock.name:
                names.append(m._semlock.name)
    return names


SNAPSHOT_DIR_PREFIX = "eslam-snapshots-"


def process_exists(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's
        pass
    return True


def snapshot_directory() -> str:
    """A new directory in shared memory (RAM) for the mapper's snapshot files, named after this process. Those of
    processes that are gone are removed first: a SIGKILLed parent cannot remove its own."""
    root = "/dev/shm" if os.path.isdir("/dev/shm") else tempfile.gettempdir()
    for path in glob.glob(os.path.join(root, SNAPSHOT_DIR_PREFIX + "*")):
        pid = os.path.basename(path)[len(SNAPSHOT_DIR_PREFIX):].split("-")[0]
        if pid.isdigit() and not process_exists(int(pid)):
            shutil.rmtree(path, ignore_errors=True)
    return tempfile.mkdtemp(prefix=f"{SNAPSHOT_DIR_PREFIX}{os.getpid()}-", dir=root)


def read_snapshot(state: str | bytes) -> dict:
    """The scene map's state from the mapper's answer: a file it wrote (mapped, then removed: the mapped pages stay
    until the tensors go) or bytes."""
    if isinstance(state, bytes):
        return torch.load(io.BytesIO(state), weights_only=True)
    try:
        return torch.load(state, weights_only=True, mmap=True)
    finally:
        os.unlink(state)


class MultiProcessRuntime(SavingMixin):
    def __init__(self, cfg: Config, intrinsics: Intrinsics, policy: str = "offline", threads: Optional[int] = None,
                 checkpoint: Optional[str] = None):
        """threads: torch threads per worker. The rest of the tuning is the config's runtime section (capacity:
        frames in the input ring; publish_every, lend_threads, keyframe_backlog, catch_up_iterations, ...: see
        config.py and workers.py), checked with the config."""
        self.cfg = cfg
        self.intrinsics = intrinsics
        self.policy = check_policy(policy)
        self.threads = threads or cfg.run.threads or default_threads()
        if self.threads < 1:
            raise RuntimeSetupError(f"threads ({self.threads}) must be at least 1")
        self.checkpoint = checkpoint  # a saved map the first epoch starts from; checked here, loaded by the workers
        self._loaded_trajectory = loaded_trajectory(checkpoint, cfg, intrinsics).state_dict() if checkpoint \
            else None
        self._hung: set = set()
        self.work_intr = working_intrinsics(intrinsics, cfg.camera)
        self._started = self._closed = False
        self._lock = threading.RLock()  # parent-side state: mirror, pending updates, meters
        # One thread at a time takes the workers' messages (in order); the wait for the first one holds only this
        # lock, so that a thread waiting for poses (poll with a timeout) does not hold up readers of the state.
        self._reading = threading.Lock()
        self._answering = threading.Lock()
        self._submit_lock = threading.Lock()  # the frame ring has a single writer
        self._crash: Optional[RuntimeCrashed] = None
        self._expected_exit = False
        self._final: Optional[SLAM] = None
        self._last_health: Optional[Health] = None  # kept by close(), when the shared counters go away
        self._last_counters: dict = {}
        self._worker_pids: dict[str, int] = {}
        self._semaphores: list[str] = []
        self._request_ids = itertools.count()
        self._reset_parent_state(epoch=0)

    def _reset_parent_state(self, epoch: int) -> None:
        self._epoch = epoch
        self._parent = ParentState(TrackedTrajectory.from_state_dict(self._loaded_trajectory) if epoch == 0 and
                                   self._loaded_trajectory else None)
        self._tracker_finished = self._mapper_finished = False
        self._snapshots: dict[int, MapperSnapshot] = {}  # answers taken from the queue, by request id

    # ----------------------------------------------------------------------------------------------- start-up
    def start(self) -> None:
        if self._started:
            raise RuntimeSetupError("the runtime is already started (start() is called once; use reset() to begin "
                                    "a new map)")
        self._started = True
        ctx = tmp.get_context("spawn")
        self._ring = FrameRing(self.cfg.runtime.capacity, self.work_intr.height, self.work_intr.width, ctx)
        self._board = HealthBoard()
        self._control = Control()
        self._map_meta = MapMeta(ctx)
        self._queues = {name: ctx.Queue() for name in ("to_mapper", "to_tracker", "to_parent", "commands", "answers")}
        q = self._queues
        self._channels = Channels(self._ring, q["to_mapper"], q["to_tracker"], q["to_parent"], q["commands"],
                                  q["answers"], self._board, self._control, self._map_meta)
        self._semaphores = semaphore_names(self._ring.cond, self._map_meta.lock, *self._queues.values())
        self._snapshot_dir = snapshot_directory()
        setup = WorkerSetup(self.cfg, self.intrinsics, self.policy, self.threads, os.getpid(),
                            logging.getLogger("eslam").getEffectiveLevel(), os.environ.get("ESLAM_FAULT", ""),
                            self.checkpoint)
        self._errors, self._processes, error_ends = {}, {}, {}
        for name, main in (("tracker", tracker_main), ("mapper", mapper_main)):
            self._errors[name], error_ends[name] = ctx.Pipe(duplex=False)
            self._processes[name] = ctx.Process(target=main, args=(setup, self._channels, error_ends[name]),
                                                name=f"eslam-{name}", daemon=True)
        self._wake_r, self._wake_w = ctx.Pipe(duplex=False)
        self._ready: set = set()
        spawned = threading.Event()
        self._monitor_thread = threading.Thread(target=self._monitor, args=(error_ends, spawned),
                                                name="eslam-runtime-monitor", daemon=True)
        with worker_environment(WORKER_ENV):
            self._monitor_thread.start()
            spawned.wait()
        self._worker_pids = {name: p.pid for name, p in self._processes.items() if p.pid is not None}
        try:
            if not self._wait(lambda: self._ready == set(WORKERS), START_TIMEOUT_S, "the workers to start"):
                raise RuntimeCrashed("runtime", f"the workers did not start within {START_TIMEOUT_S:.0f} s "
                                                f"(started: {sorted(self._ready) or 'none'}); is the machine swapping?")
        except BaseException:
            self._shutdown()
            self._closed = True
            raise
        log.info("runtime: tracker (pid %d) and mapper (pid %d) running, %d torch thread(s) each, %s policy",
                 self._processes["tracker"].pid, self._processes["mapper"].pid, self.threads, self.policy)

    def _monitor(self, error_ends: dict, spawned: threading.Event) -> None:
        try:
            with spawned_with_stop_signals_blocked():
                for p in self._processes.values():
                    p.start()
        except BaseException as e:  # noqa: BLE001 - reported to the caller as a crash
            self._set_crash(RuntimeCrashed("runtime", f"could not start the worker processes: {e}",
                                           traceback.format_exc()))
            return
        finally:
            for end in error_ends.values():
                end.close()  # the workers hold the write ends now: EOF here means they are gone
            spawned.set()
        watched: dict = {}
        for name, p in self._processes.items():
            watched[p.sentinel] = ("exit", name)
            watched[self._errors[name]] = ("error", name)
        tracebacks: dict = {}
        while watched:
            ready = multiprocessing.connection.wait(list(watched) + [self._wake_r], timeout=MONITOR_S)
            if self._wake_r in ready:
                return
            self._check_heartbeats()
            # Error pipes first: a traceback is written before its process exits.
            for obj in sorted(ready, key=lambda o: watched[o][0] != "error"):
                kind, name = watched.pop(obj)
                if kind == "error":
                    try:
                        tracebacks[name] = obj.recv()
                    except (EOFError, OSError):
                        pass
                elif not self._expected_exit:
                    self._on_worker_exit(name, tracebacks)

    def _check_heartbeats(self) -> None:
        """Kill a worker that shows no sign of life (a deadlock, a stuck system call): nothing may hang."""
        if self._expected_exit or self._crash is not None or self._ready != set(WORKERS):
            return
        now = time.monotonic()
        for name, beat in (("tracker", Counter.TRACKER_BEAT), ("mapper", Counter.MAPPER_BEAT)):
            last = self._board.get(beat)
            if last > 0 and now - last > HANG_S and name not in self._hung:
                self._hung.add(name)
                log.error("runtime: the %s shows no sign of life for %.0f s; killing it", name, now - last)
                self._processes[name].kill()

    def _on_worker_exit(self, name: str, tracebacks: dict) -> None:
        p = self._processes[name]
        p.join(1.0)
        code = p.exitcode
        text = tracebacks.get(name, "")
        if not text and self._errors[name].poll(0.5):
            try:
                text = self._errors[name].recv()
            except (EOFError, OSError):
                pass
        if code is not None and code < 0:
            sig = signal.Signals(-code).name
            summary = f"the {name} process was killed by {sig}" + \
                (" (the kernel's out-of-memory killer sends SIGKILL)" if -code == signal.SIGKILL else "")
        elif code == EXIT_ORPHANED:
            summary = f"the {name} process exited because it lost its parent"
        elif name in self._hung:
            summary = f"the {name} process hung (no sign of life for {HANG_S:.0f} s) and was killed"
        else:
            summary = f"the {name} process failed (exit code {code})"
        if not text:
            text = "(no traceback: it died without reporting one; look for its output above)"
            if name not in self._ready:
                text += ("\nIt died while starting. Spawned workers import the main module of this program: a script "
                         "that starts the runtime must do so under `if __name__ == '__main__':`.")
        self._set_crash(RuntimeCrashed(name, summary, text))
        # Bring the rest down: a runtime with one worker is no runtime.
        self._control.request_exit()
        for other, q in self._processes.items():
            if other != name and q.is_alive():
                q.join(1.0)
                if q.is_alive():
                    q.kill()  # workers ignore SIGTERM

    def _set_crash(self, crash: RuntimeCrashed) -> None:
        with self._lock:
            if self._crash is not None:
                return
            self._crash = crash
        log.error("%s\n%s", crash.summary, crash.traceback)

    def _raise_if_crashed(self) -> None:
        if self._crash is not None:
            raise self._crash

    def _check_running(self) -> None:
        if not self._started:
            raise RuntimeSetupError("the runtime is not started: call start() first (or use it in a `with` block)")
        if self._closed:
            raise RuntimeSetupError("the runtime is closed: make a new one with make_runtime()")
        self._raise_if_crashed()

    # -------------------------------------------------------------------------------------------- messages in
    def _pump(self, block_s: float = 0.0, take_turn: bool = False) -> None:
        """Take every message the workers sent the parent (waiting up to `block_s` for the first). A call that
        neither waits nor `take_turn`s returns at once while another thread is taking messages: that one handles
        them."""
        q = self._queues["to_parent"]
        if not self._reading.acquire(blocking=block_s > 0 or take_turn):
            return
        try:
            try:
                msg = q.get(timeout=block_s) if block_s > 0 else q.get_nowait()
            except queue.Empty:
                return
            with self._lock:
                while True:
                    self._handle(msg)
                    try:
                        msg = q.get_nowait()
                    except queue.Empty:
                        return
        finally:
            self._reading.release()

    def _handle(self, msg) -> None:
        if isinstance(msg, WorkerReady):
            self._ready.add(msg.worker)
            return
        if msg.epoch != self._epoch:
            return  # from before a reset
        if isinstance(msg, TrackedFrame):
            self._parent.posed(msg.record, msg.keyframe, msg.keyframe, msg.latency_s, msg.done)
        elif isinstance(msg, MappingReport):
            self._parent.mapped(msg.refined, msg.done)
        elif isinstance(msg, LoopClosed):
            self._parent.corrected(msg.refined)
        elif isinstance(msg, TrackerFinished):
            self._tracker_finished = True
        elif isinstance(msg, MapperFinished):
            self._mapper_finished = True

    def _wait(self, done: Callable[[], bool], timeout: Optional[float], what: str) -> bool:
        """Pump messages until `done()`; raises RuntimeCrashed if a worker dies meanwhile, returns False when
        `timeout` (seconds, None = no limit) runs out."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            self._raise_if_crashed()
            self._pump(block_s=0.05)
            if done():
                return True
            if deadline is not None and time.monotonic() > deadline:
                log.debug("runtime: gave up waiting for %s after %.0f s", what, timeout)
                return False

    # ------------------------------------------------------------------------------------------------ the API
    def submit(self, frame: Frame) -> None:
        self._check_running()
        check_frame(frame, self.intrinsics)
        with self._lock:
            self._parent.submitted(frame.index, frame.tag)
        arrival = time.monotonic()
        rgb8, depth = working_images(frame, self.intrinsics, self.cfg.camera)
        live = self.policy == "live"
        with self._submit_lock:
            self._board.add(Counter.RECEIVED)
            while True:
                written, evicted = self._ring.put(rgb8, depth, frame.index, frame.timestamp, frame.pose,
                                                  arrival, live, timeout=0.1, odom_pose=frame.odom_pose)
                if evicted:
                    self._board.add(Counter.DROPPED_AT_SUBMIT, evicted)
                if written:
                    return
                self._raise_if_crashed()
                if self._control.stopping:  # close(drain=False) from another thread: the ring will not empty
                    self._board.add(Counter.DROPPED_AT_SUBMIT)
                    return

    def poll(self, timeout: float = 0.0) -> list[PoseUpdate]:
        if self._started and not self._closed:
            self._raise_if_crashed()
            self._pump()
            deadline = time.monotonic() + timeout
            while not self._parent.updates and time.monotonic() < deadline:  # (other messages may come first)
                self._pump(block_s=min(deadline - time.monotonic(), 0.05))
                self._raise_if_crashed()
        with self._lock:
            return self._parent.take_updates()

    def trajectory(self, max_poses: Optional[int] = None) -> tuple[np.ndarray, np.ndarray]:
        if self._final is not None:
            return self._final.trajectory.timestamps(max_poses), self._final.trajectory.poses(max_poses)
        if self._started and not self._closed:
            self._raise_if_crashed()
            self._pump()
        with self._lock:
            return self._parent.trajectory.timestamps(max_poses), self._parent.trajectory.poses(max_poses)

    def health(self) -> Health:
        if self._last_health is not None:
            return self._last_health
        if not self._started:
            return Health(0, 0, 0, 0, 0.0, 0.0, 0, 0, 0, 0.0, 0.0)
        self._pump()
        return self._health_now()

    def _health_now(self) -> Health:
        b = self._board
        with self._lock:
            return Health(
                frames_received=int(b.get(Counter.RECEIVED)),
                frames_tracked=int(b.get(Counter.TRACKED)),
                frames_dropped=int(b.get(Counter.DROPPED_AT_SUBMIT) + b.get(Counter.DROPPED_BY_TRACKER)),
                input_queue_depth=self._ring.pending(),
                keyframe_queue_depth=b.unmapped_keyframes(),
                map_version=self._map_meta.version,
                map_publish_ms=1000.0 * b.get(Counter.PUBLISH_SECONDS) / max(b.get(Counter.PUBLISHES), 1.0),
                map_read_ms=1000.0 * b.get(Counter.READ_SECONDS) / max(b.get(Counter.READS), 1.0),
                map_bytes=int(b.get(Counter.MAP_BYTES)), keyframe_bytes=int(b.get(Counter.KEYFRAME_BYTES)),
                keyframes_kept=int(b.get(Counter.KEYFRAMES_KEPT)),
                submaps=max(1, int(b.get(Counter.SUBMAPS))), loops_closed=int(b.get(Counter.LOOPS_CLOSED)),
                loop_correction_s=b.get(Counter.LOOP_CORRECTION_S) if b.get(Counter.LOOPS_CLOSED) else math.nan,
                consistency_mm=b.get(Counter.CONSISTENCY_MM) if b.get(Counter.CONSISTENCY_PAIRS) else math.nan,
                consistency_agree=b.get(Counter.CONSISTENCY_AGREE) if b.get(Counter.CONSISTENCY_PAIRS) else math.nan,
                map_disagreement_cm=b.get(Counter.MAP_CHECK_CM) if b.get(Counter.MAP_CHECK) else math.nan,
                map_disagrees=b.get(Counter.MAP_CHECK) == 2,
                peak_memory_mb={"parent": peak_rss_mb(), "tracker": b.get(Counter.TRACKER_PEAK_MB),
                                "mapper": b.get(Counter.MAPPER_PEAK_MB)},
                stage_ms={row["stage"]: round(row["ms"], 2) for row in stage_profile(b.snapshot())
                          if not math.isnan(row["ms"])},
                **self._parent.health_figures(),  # keyframes: in the current map
            )

    def worker_figures(self) -> dict:
        """Raw counters of the workers (peak memory per process, map copies, points outside the bound)."""
        if self._closed or not self._started:
            return dict(self._last_counters)
        return self._board.snapshot()

    def snapshot(self) -> SLAM:
        """The current state as a `SLAM` (map, keyframes and trajectory so far); after close(), the final one."""
        if self._final is not None:
            return self._final
        self._check_running()
        self._pump(take_turn=True)
        with self._lock:
            # (in localization every frame anchors the trajectory, and no keyframe goes to the mapper)
            keyframes = self._parent.trajectory.keyframes if self.cfg.run.mode == "slam" else 0
            trajectory, epoch = self._parent.trajectory.state_dict(), self._epoch
        path = os.path.join(self._snapshot_dir, "{}.pt")
        state = self._ask_mapper(lambda request_id: SnapshotRequest(request_id, epoch, keyframes,
                                                                    path.format(request_id)), "a snapshot of the map")
        slam = SLAM(self.cfg, self.intrinsics)
        if state is not None:  # else reset meanwhile, or nothing tracked yet
            state = read_snapshot(state)
            if "atlas" in state:
                slam.atlas = Atlas(slam.cfg, slam.intr, slam.dirs_cam)
                slam.atlas.load_state_dict(state["atlas"])
            else:
                slam.atlas.load_single_map(state)
            slam.tracking.trajectory = TrackedTrajectory.from_state_dict(trajectory)
        return slam

    def _ask_mapper(self, request: Callable[[int], object], what: str):
        """Send the mapper `request(request_id)` and wait for its answer (`MapperSnapshot.state`)."""
        with self._lock:
            request_id = next(self._request_ids)
        self._queues["commands"].put(request(request_id))
        deadline = time.monotonic() + SNAPSHOT_TIMEOUT_S
        while True:
            self._raise_if_crashed()
            with self._answering:  # answers to several asking threads: each takes its own from the dict
                if request_id in self._snapshots:
                    return self._snapshots.pop(request_id).state
                try:
                    msg = self._queues["answers"].get(timeout=0.05)
                    if msg.epoch == self._epoch:  # (an answer from before a reset is dropped)
                        self._snapshots[msg.request_id] = msg
                except queue.Empty:
                    pass
            if time.monotonic() > deadline:
                raise RuntimeCrashed("mapper", f"the mapper did not send {what} within {SNAPSHOT_TIMEOUT_S:.0f} s")

    def mesh_snapshot(self, have: set):
        if self._final is not None:
            return snapshot_for_meshing(self._final.atlas, have)
        self._check_running()
        epoch = self._epoch
        snapshot = self._ask_mapper(lambda request_id: MeshRequest(request_id, epoch, set(have)), "the map for a mesh")
        if snapshot is None:
            raise EmptyMeshError("the map is empty: no keyframe has been mapped yet")
        return snapshot

    def reset(self) -> None:
        self._check_running()
        with self._submit_lock, self._lock:
            # Pending frames first, then the epoch: a frame the tracker takes from now on is a new-epoch frame.
            self._board.add(Counter.DROPPED_AT_SUBMIT, self._ring.discard_pending())
            self._reset_parent_state(self._control.new_epoch())

    # ---------------------------------------------------------------------------------------------- shutdown
    def close(self, timeout: float | None = None, drain: Optional[bool] = None) -> None:
        """Finish (offline: every submitted frame; `drain=False`: stop now), keep the final state for
        `trajectory()` / `save_*()` / `snapshot()`, stop the workers and release the shared memory.

        `timeout`: seconds to wait for the work to finish before stopping now anyway (None = as long as it takes;
        with drain=False there is no work to wait for). Stopping now takes at most one tracked frame plus one
        optimiser iteration.
        Idempotent: later calls do nothing. Raises RuntimeCrashed if a worker died."""
        if self._closed:
            return
        if not self._started:
            self._closed = True
            return
        drain = self.policy == "offline" if drain is None else drain
        crash = None
        try:
            self._raise_if_crashed()
            self._ring.close_input()
            finished = lambda: self._tracker_finished and self._mapper_finished  # noqa: E731
            if drain and not self._wait(finished, timeout, "the workers to finish"):
                log.warning("runtime: the work did not finish within %.0f s; stopping now", timeout)
                drain = False
            if not drain:
                self._stop_now()
                if not self._wait(finished, STOP_GRACE_S, "the workers to stop"):
                    raise RuntimeCrashed("runtime", f"the workers did not stop within {STOP_GRACE_S:.0f} s of being "
                                                    f"asked to; they were killed")
            self._final = self.snapshot()
        except RuntimeCrashed as e:
            crash = e
        finally:
            self._pump(take_turn=True)
            with self._lock:
                self._last_health = self._health_now()
                self._last_counters = self._board.snapshot()
            self._shutdown()
            self._closed = True
        if crash is not None:
            raise crash

    def _stop_now(self) -> None:
        self._control.request_stop()
        with self._submit_lock:
            self._board.add(Counter.DROPPED_AT_SUBMIT, self._ring.discard_pending())

    def _shutdown(self) -> None:
        """Stop the workers (asked, then killed), stop the monitor, release everything shared."""
        self._expected_exit = True
        self._control.request_exit()
        deadline = time.monotonic() + JOIN_S
        for p in self._processes.values():
            if p.pid is not None:
                p.join(max(0.0, deadline - time.monotonic()))
        for p in self._processes.values():
            if p.pid is not None and p.is_alive():
                log.warning("runtime: %s did not exit when asked; killing it", p.name)
                p.kill()  # workers ignore SIGTERM
                p.join()
        self._wake_w.send(b"")
        self._monitor_thread.join()
        self._release()

    def _release(self) -> None:
        for q in self._queues.values():
            q.cancel_join_thread()  # never wait on a feeder thread whose reader is gone
            q.close()
        for p in self._processes.values():
            if p.pid is not None:
                p.close()
        for conn in (*self._errors.values(), self._wake_r, self._wake_w):
            conn.close()
        # Dropping the last references unlinks the semaphores and unmaps the shared tensors; some of them sit in
        # reference cycles (queues and their feeder threads), so collect now rather than at some later moment.
        self._ring = self._map_meta = self._channels = self._board = self._control = None
        shutil.rmtree(self._snapshot_dir, ignore_errors=True)  # (files of answers that came too late to be read)
        self._queues, self._processes, self._errors = {}, {}, {}
        gc.collect()

    # ------------------------------------------------------------------------------------------- diagnostics
    def resources(self) -> dict:
        """Worker pids ({"tracker": pid, "mapper": pid}), the /dev/shm entries of this runtime's semaphores and its
        snapshot directory (for tests and for debugging shutdown)."""
        return {"pids": dict(self._worker_pids), "shm": [f"/dev/shm/sem.{n.lstrip('/')}" for n in self._semaphores],
                "snapshot_dir": self._snapshot_dir}

    def __enter__(self) -> "MultiProcessRuntime":
        if not self._started:
            self.start()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None and not isinstance(exc, RuntimeCrashed):
            # Leaving on an error of the caller: stop now rather than finishing the queued work.
            try:
                self.close(drain=False)
            except RuntimeCrashed as e:
                log.error("runtime: %s", e.summary)
            return
        if exc_type is None:
            self.close()
        else:
            try:
                self.close()
            except RuntimeCrashed:
                pass  # already being raised
