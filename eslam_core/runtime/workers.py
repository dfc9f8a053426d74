"""The two worker processes of the pipelined runtime: the tracker and the mapper, and what they say to each other.

Tracker: takes frames from the shared frame ring and drives the tracking session of the lock-step `SLAM`
(`tracking/session.py`) against a replica of the mapper's map: every frame is tracked against the newest map version
it can see, stored relative to its keyframe, and every keyframe is handed to the mapper (uint8 colour and 16-bit
depth, as `Keyframe` stores them) instead of being mapped. It never waits for the mapper, except once: frame 1 needs
the map of frame 0 (the warm-up), as in the lock-step schedule, or with `runtime.first_map_after` the map after that
many of the warm-up's iterations. The mapper's corrections (refined keyframe poses, dropped keyframes) come back and
are applied to the session, as in `SLAM`.

Mapper: owns the `SceneField`. It starts the map from keyframe 0 (bound chosen by the tracker from that frame),
runs the warm-up, then one mapping step per keyframe, within its budget (`budget.py`: when waiting keyframes join
the newest one's window, when a step ends early). After each step (and, with `publish_every`, every so many
iterations during one) it publishes the parameters into the shared map.
The publishing and the checks for stop / reset / snapshot requests happen after every mapping iteration (the
callback `Mapper.map` calls, `_after_iteration`), so that a long step (the warm-up) still reacts within one
iteration.

Cores: each worker owns `threads` torch threads (the machine's cores split between the two). While one worker is
idle (the tracker during the warm-up or without frames, the mapper without keyframes), its threads are lent to the
other (`CoreShare`, checked before every frame or step and after every mapping iteration), so that the warm-up and
the end of a run are not slower than in the lock-step schedule, which uses every core for whatever it does.

Both workers: ignore SIGINT and SIGTERM (Ctrl-C reaches the whole process group, and service managers send SIGTERM
to every process of a service: stopping is the parent's decision, which asks them, or SIGKILLs them), die with their
parent (Linux
PR_SET_PDEATHSIG plus a thread watching the parent pid), set their own torch thread count, and on any exception
send their traceback to the parent through a pipe and exit with code 1.

Fault injection (a testing aid): ESLAM_FAULT="tracker:5" makes the tracker fail when it is about to track its
frame number 5 (counting from 0), "mapper:3" makes the mapper fail at the start of its mapping step number 3 (the
warm-up is step 0). Append ":kill" to die by SIGKILL instead of raising, ":oom" to raise MemoryError. Several
faults are separated by commas.
"""
from __future__ import annotations

import copy
import dataclasses
import io
import logging
import os
import queue
import signal
import sys
import time
import traceback
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Optional

import cv2
import numpy as np
import torch

from eslam_core.camera import Frame, Intrinsics
from eslam_core.config import Config
from eslam_core.device import peak_memory_mb as device_peak_mb, resolve_device
from eslam_core.child_process import become_child
from eslam_core.cpu import FullCollections, PeriodicRelease, freeze_start_up_objects, lower_priority
from eslam_core.frames import PreparedFrame, pixel_directions_table, prepare_frame, working_intrinsics
from eslam_core.mapping.keyframes import Keyframe
from eslam_core.mapping.mapper import import_optimiser_code
from eslam_core.mapping.observed import ObservedSurfaces
from eslam_core.mapping.scene_map import SceneMap, surface_points
from eslam_core.native import load_kernel
from eslam_core.atomic import atomic_output
from eslam_core.representation.field import SceneField
from eslam_core.runtime.mesher import PackedSnapshot, snapshot_for_meshing
from eslam_core.runtime.api import peak_rss_mb
from eslam_core.runtime.budget import MappingBudget
from eslam_core.slam import loaded_slam
from eslam_core.submaps.atlas import Atlas
from eslam_core.tracking.frontend import TrackedPose, TrackingFrontEnd
from eslam_core.tracking.places import KeyframePlaces
from eslam_core.tracking.session import PoseCorrections, Tracked, TrackingSession
from eslam_core.trajectory import FrameRecord, TrackedTrajectory
from eslam_core.runtime.shared import Control, Counter, FrameRing, HealthBoard, MapMeta, SharedMap

log = logging.getLogger("eslam")

EXIT_CRASHED = 1
POLL_S = 0.05  # how often idle workers look at their flags and queues
# Keyframes handed over whose surface points the tracker keeps: a submap the mapper attaches it to holds those it
# had received; the mapper is never more than a few keyframes behind when it begins a submap.
HANDED_KEPT = 8
FOLLOW_EVERY = 15  # frames between two reports of a localizing tracker's position to the mapper


# ------------------------------------------------------------------------------------------------------ messages

@dataclass
class WorkerReady:
    worker: str
    pid: int


@dataclass
class KeyframeMessage:  # tracker -> mapper
    epoch: int
    number: int  # keyframe number (0, 1, ... in order of creation)
    frame_index: int
    timestamp: float
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) int16 (uint16 bits, see keyframes.DEPTH_STEP)
    usable: np.ndarray  # (H, W) bool
    pose: np.ndarray  # (4, 4) float32
    extent: Optional[np.ndarray]  # with keyframe 0: the extent the map starts with

    @staticmethod
    def of(epoch: int, kf: Keyframe, extent: Optional[np.ndarray]) -> "KeyframeMessage":
        return KeyframeMessage(epoch, kf.number, kf.frame_index, kf.timestamp, kf.rgb.numpy(), kf.depth.numpy(),
                               kf.usable.numpy(), kf.pose.numpy(), extent)

    def keyframe(self) -> Keyframe:
        return Keyframe(self.frame_index, self.timestamp, torch.from_numpy(self.rgb), torch.from_numpy(self.depth),
                        torch.from_numpy(self.usable), torch.from_numpy(self.pose), self.number)


@dataclass
class TrackedFrame:  # tracker -> parent
    epoch: int
    record: FrameRecord  # the pose as tracked, and relative to its keyframe
    keyframe: bool
    latency_s: float
    done: float  # time.monotonic() when the pose was available


@dataclass
class TrackerFinished:  # tracker -> mapper and parent: no more frames (input drained, or told to stop)
    epoch: int
    frames: int
    keyframes: int


@dataclass
class MapAttach:  # mapper -> tracker, after the warm-up and every growth: where the map is, and its extent
    epoch: int
    buffers: torch.Tensor
    generation: int
    extent: np.ndarray
    # With submaps (submaps/atlas.py), also after the active submap changed or moved: its number and anchor (None:
    # the world's frame); when it changed, a copy of its observed space and the newest keyframe number it holds
    # (the tracker adds the keyframes it handed over since).
    submap: int = 0
    anchor: Optional[np.ndarray] = None
    observed: Optional[ObservedSurfaces] = None
    holds: int = -1


@dataclass
class CameraAt:  # tracker -> mapper, localization with submaps: where the camera is (for Atlas.follow)
    epoch: int
    position: np.ndarray  # (3,) world
    found_by: Optional[int]  # the keyframe whose features found it (a relocalization), if any


@dataclass
class Corrections:  # mapper -> tracker
    epoch: int
    corrections: PoseCorrections  # refined keyframe poses ((4, 4) float32), keyframes the store dropped


@dataclass
class LoopClosed:  # mapper -> parent: the keyframe poses a loop closure moved (submaps/atlas.py)
    epoch: int
    refined: dict


@dataclass
class PlacesMessage:  # mapper -> tracker: keyframes indexed for relocalization, with their map checks
    epoch: int
    indexed: list  # of places.Indexed


@dataclass
class MappingReport:  # mapper -> parent, after every mapping step
    epoch: int
    step: int
    version: int
    loss: float
    seconds: float
    done: float
    refined: dict


@dataclass
class MapperFinished:  # mapper -> parent: every keyframe the tracker made is mapped (or stop was asked)
    epoch: int


@dataclass
class SnapshotRequest:  # parent -> mapper
    request_id: int
    epoch: int
    min_keyframes: int
    path: str = ""  # where to write the state (a file in shared memory), "" to send it through the queue


@dataclass
class MeshRequest:  # parent -> mapper
    request_id: int
    epoch: int
    have: set  # keyframe ids whose depth images the mesh process has


@dataclass
class MapperSnapshot:  # mapper -> parent
    request_id: int
    epoch: int
    # SceneMap.state_dict() written by torch.save to the request's path (the path answers), or as bytes when it
    # has none or the write failed; or the PackedSnapshot of a MeshRequest; None before keyframe 0
    state: Any


# ------------------------------------------------------------------------------------------------- set-up, faults

@dataclass
class WorkerSetup:
    cfg: Config
    intrinsics: Intrinsics  # of the frames as submitted
    policy: str
    threads: int
    parent_pid: int
    log_level: int
    faults: str = ""  # ESLAM_FAULT (FaultPlan)
    checkpoint: Optional[str] = None  # a saved map the first epoch starts from (see slam.loaded_slam)


@dataclass
class Channels:
    ring: FrameRing
    to_mapper: Any  # queue: KeyframeMessage, TrackerFinished
    to_tracker: Any  # queue: MapAttach, Corrections
    to_parent: Any  # queue: WorkerReady, TrackedFrame, MappingReport, ...
    commands: Any  # queue, parent -> mapper: SnapshotRequest, MeshRequest
    # queue, mapper -> parent: MapperSnapshot. Not to_parent: a queue is one pipe behind one write lock, and the
    # tracker's poses waited behind a map of megabytes written by a niced mapper (stalls of 0.5-0.7 s per mesh).
    answers: Any
    board: HealthBoard
    control: Control
    map_meta: MapMeta


class InjectedFault(RuntimeError):
    """Raised on purpose by ESLAM_FAULT (testing aid)."""


@dataclass(frozen=True)
class FaultPlan:
    steps: dict = field(default_factory=dict)  # worker -> (step, mode)

    @staticmethod
    def parse(text: str) -> "FaultPlan":
        steps = {}
        for item in filter(None, (s.strip() for s in text.split(","))):
            parts = item.split(":")
            if len(parts) not in (2, 3) or parts[0] not in ("tracker", "mapper") or not parts[1].isdigit() or \
                    (len(parts) == 3 and parts[2] not in ("raise", "kill", "oom")):
                raise ValueError(f"ESLAM_FAULT={text!r}: each fault is worker:step[:mode] with worker tracker or "
                                 f"mapper and mode raise, kill or oom (e.g. mapper:3 or tracker:5:kill)")
            steps[parts[0]] = (int(parts[1]), parts[2] if len(parts) == 3 else "raise")
        return FaultPlan(steps)

    def check(self, worker: str, step: int) -> None:
        if worker not in self.steps or self.steps[worker][0] != step:
            return
        mode = self.steps[worker][1]
        if mode == "kill":
            os.kill(os.getpid(), signal.SIGKILL)
        if mode == "oom":
            raise MemoryError(f"injected out-of-memory in the {worker} at step {step} (ESLAM_FAULT)")
        raise InjectedFault(f"injected fault in the {worker} at step {step} (ESLAM_FAULT)")


def become_worker(name: str, setup: WorkerSetup) -> None:
    become_child(name, setup.parent_pid)
    logging.basicConfig(level=setup.log_level, format=f"%(levelname)s eslam.{name}: %(message)s")
    torch.set_num_threads(setup.threads)
    cv2.setNumThreads(setup.threads)  # OpenCV's pool (odometry, ORB) would otherwise take the other worker's core
    torch.manual_seed(setup.cfg.run.seed)
    for kernel in ("plane_lookup", "photometric", "gauss_newton"):  # now, not inside the first frame's timing
        load_kernel(kernel)


def started_up() -> FullCollections:
    """A worker's start-up done: its objects so far frozen (cpu.freeze_start_up_objects), the full collections
    from now on timed."""
    freeze_start_up_objects()
    return FullCollections()


def run_worker(name: str, body, setup: WorkerSetup, errors) -> None:
    """Run a worker's main loop; on any failure send the traceback to the parent and exit non-zero."""
    code = 0
    try:
        become_worker(name, setup)
        body()
    except BaseException:  # noqa: BLE001 - whatever it was, the parent must hear about it
        code = EXIT_CRASHED
        try:
            errors.send(traceback.format_exc())
        except OSError:
            pass
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        # Skip interpreter teardown: queue feeder threads would wait for a parent that may no longer read.
        os._exit(code)


def working_setup(cfg: Config, intrinsics: Intrinsics) -> tuple[Config, Intrinsics]:
    """The config and camera of frames that are already at the working resolution (as in the frame ring)."""
    return dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, image_scale=1.0)), \
        working_intrinsics(intrinsics, cfg.camera)


def _get(q, timeout: float):
    try:
        return q.get(timeout=timeout) if timeout > 0 else q.get_nowait()
    except queue.Empty:
        return None


class CoreShare:
    """A worker's torch threads: its own share, plus the other worker's while that one is idle."""

    def __init__(self, board: HealthBoard, mine: Counter, other: Counter, beat: Counter, threads: int, lend: bool):
        self.board, self.mine, self.other, self.beat = board, mine, other, beat
        self.threads, self.lend = threads, lend

    def busy(self, flag: bool) -> None:
        self.board.set(self.mine, float(flag))
        self.update()

    def update(self) -> None:
        """Also the worker's heartbeat: called at least once per loop pass and optimiser iteration."""
        self.board.set(self.beat, time.monotonic())
        lent = self.threads if self.lend and self.board.get(self.other) == 0 else 0
        if torch.get_num_threads() != self.threads + lent:
            torch.set_num_threads(self.threads + lent)


class Interrupted(Exception):
    """The parent asked to stop, exit or reset while a worker was waiting or in the middle of a step."""


# ------------------------------------------------------------------------------------------------------- tracker

class MapReplica:
    """The tracking process's view of the mapper's map (a `MapView`): a copy of the field refreshed from shared
    memory, its extent, observed space fed by the keyframes as mapping fits them, and the newest keyframe (its
    images, for the SDF tracker's photometric term; the mapper keeps every keyframe's)."""

    def __init__(self, cfg: Config, intr: Intrinsics, dirs_cam: torch.Tensor):
        self.cfg, self.intr, self.dirs_cam = cfg, intr, dirs_cam
        self.device = resolve_device(cfg.run.device)  # the mapper's map lives there too
        self.extent: Optional[np.ndarray] = None
        self.field: Optional[SceneField] = None
        self.version = 0  # of the field's values: counts the changes (new fields, versions copied in)
        self.observed: Optional[ObservedSurfaces] = None
        self.newest: Optional[Keyframe] = None  # (its world pose)
        # With submaps: the active one's number and anchor (its frame's world pose; None: the world's frame), and
        # the surface points (world) of the newest keyframes handed over, which a submap attached later may lack.
        self.submap = 0
        self.anchor: Optional[np.ndarray] = None
        self.handed: deque = deque(maxlen=HANDED_KEPT if cfg.submaps.radius_m > 0 else 0)

    @property
    def started(self) -> bool:
        return self.field is not None

    def start(self, extent: np.ndarray) -> None:
        self.extent = extent
        self.field = SceneField(extent, self.cfg.model, self.device)
        self.version += 1
        self.observed = ObservedSurfaces(extent, self.cfg.model.truncation, self.device,
                                         self.cfg.sdf_tracker.observed_after)

    def attach(self, msg: MapAttach) -> None:
        """The mapper's map over `msg.extent` (grown, or as started): a field of that size to copy it into; with
        submaps, another submap (its observed space as the mapper has it, plus the keyframes handed over since) or
        the same one moved."""
        self.anchor = msg.anchor
        if msg.observed is not None:
            self.submap, self.extent = msg.submap, np.asarray(msg.extent)
            self.field = SceneField(self.extent, self.cfg.model, self.device)
            self.version += 1
            self.observed = msg.observed
            for number, points in self.handed:
                if number > msg.holds:
                    self.observed.add_keyframe(self._local(points))
        elif not np.array_equal(msg.extent, self.extent):
            self.extent = np.asarray(msg.extent)
            self.field = SceneField(self.extent, self.cfg.model, self.device)
            self.version += 1
            self.observed.grow(self.extent)

    def _local(self, points: torch.Tensor) -> torch.Tensor:
        """World points in the map's frame."""
        if self.anchor is None:
            return points
        to_local = torch.from_numpy(np.linalg.inv(self.anchor)).to(points.dtype)
        return points @ to_local[:3, :3].T + to_local[:3, 3]

    def refresh(self, shared: SharedMap, known: Optional[int]) -> Optional[int]:
        """Copy the shared map into the field if it holds a version newer than `known`; that version, or None."""
        version = shared.read_into(self.field, known)
        if version is not None:
            self.version += 1
        return version

    def add_keyframe(self, kf: Keyframe) -> None:
        self.newest = kf
        points = surface_points(self.dirs_cam, kf, self.intr.width)
        self.handed.append((kf.number, points))
        self.observed.add_keyframe(self._local(points))

    def refine(self, poses: dict) -> None:
        if self.newest is not None and self.newest.number in poses:
            self.newest.pose = torch.from_numpy(poses[self.newest.number])

    def newest_keyframe(self) -> Optional[Keyframe]:
        """The newest keyframe handed over, its pose in the map's frame."""
        if self.newest is None or self.anchor is None:
            return self.newest
        return self.newest.moved(np.linalg.inv(self.anchor))


class TrackerWorker:
    def __init__(self, setup: WorkerSetup, ch: Channels):
        self.setup = setup
        self.ch = ch
        self.live = setup.policy == "live"
        self.faults = FaultPlan.parse(setup.faults)
        self.cfg, self.intr = working_setup(setup.cfg, setup.intrinsics)
        self.dirs_cam = pixel_directions_table(self.intr)
        self.epoch = ch.control.epoch
        self._new_state()
        self.tracked = 0
        self.localizing = setup.cfg.run.mode == "localization" and setup.cfg.submaps.radius_m > 0
        self.asked_at = -FOLLOW_EVERY  # (the frame count when it last asked the mapper for another submap)
        self.finished = False
        self.cores = CoreShare(ch.board, Counter.TRACKER_BUSY, Counter.MAPPER_BUSY, Counter.TRACKER_BEAT,
                               setup.threads, setup.cfg.runtime.lend_threads)

    def _new_state(self) -> None:
        # The caller's copy of the trajectory has every field; this one what tracking reads back. The mapper
        # closes the loops (with submaps), from its own map checks.
        frontend = TrackingFrontEnd(self.cfg, self.intr, self.dirs_cam, closes_loops=False)
        self.session = TrackingSession(self.cfg, self.intr, self.dirs_cam, TrackedTrajectory(essential=True),
                                       frontend)
        self.replica = MapReplica(self.cfg, self.intr, self.dirs_cam)
        self.map: Optional[SharedMap] = None
        self.map_version = -1
        if self.epoch == 0 and self.setup.checkpoint:  # the mapper publishes the loaded map and attaches us to it
            loaded = loaded_slam(self.setup.checkpoint, self.setup.cfg, self.setup.intrinsics)
            self.replica.start(loaded.map.extent)  # (the active submap's: the mapper's MapAttach says which)
            for kf in loaded.atlas.to_world_keyframes(loaded.map):
                self.replica.add_keyframe(kf)
            frontend.start_lost(loaded.atlas.world_keyframes())
            self.session = TrackingSession(self.cfg, self.intr, self.dirs_cam, TrackedTrajectory.from_state_dict(
                loaded.trajectory.state_dict(), essential=True), frontend)

    def run(self) -> None:
        self.ch.to_parent.put(WorkerReady("tracker", os.getpid()))
        memory, collections = PeriodicRelease(), started_up()
        while not self.ch.control.exiting:
            self.cores.update()
            memory.release()
            self.ch.board.set(Counter.TRACK_GC_S, collections.seconds)
            self._sync_epoch()
            self._receive(0.0)
            if self.finished:
                time.sleep(POLL_S)
                continue
            if self.ch.control.stopping or self.ch.ring.drained():
                self._finish()
                continue
            waiting = self.session.idle_work  # keyframes to index for relocalization, map checks
            frame, skipped = self.ch.ring.take(self.live, 0.0 if waiting else POLL_S, self.cfg.runtime.live_backlog)
            if skipped:
                self.ch.board.add(Counter.DROPPED_BY_TRACKER, skipped)
            if frame is None:
                if not (waiting and self._index_idle()):
                    self.cores.busy(False)
                continue
            self._sync_epoch()  # a reset between the last check and this frame: track it in the new epoch
            try:
                self._track(frame)
            except Interrupted:
                self.ch.board.add(Counter.DROPPED_BY_TRACKER)  # taken, never tracked

    def _index_idle(self) -> bool:
        """A loaded map's keyframes, indexed while idle (the mapper indexes the new ones: see PlacesMessage)."""
        with self.ch.board.timed(Counter.TRACK_INDEX_S):
            return self.session.index_next()

    def _sync_epoch(self) -> None:
        epoch = self.ch.control.epoch
        if epoch != self.epoch:
            self.epoch = epoch
            self._new_state()

    def _receive(self, timeout: float) -> None:
        # The mapper only speaks of an epoch after this worker sent it that epoch's first keyframe, so a message is
        # never newer than this worker's epoch: older ones (from before a reset) are dropped.
        msg = _get(self.ch.to_tracker, timeout)
        while msg is not None:
            if msg.epoch == self.epoch:
                if isinstance(msg, MapAttach):
                    self.map = SharedMap(self.ch.map_meta, msg.buffers, msg.generation)
                    self.replica.attach(msg)
                    self.map_version = -1
                elif isinstance(msg, Corrections):
                    self.session.apply(msg.corrections)
                    self.replica.refine(msg.corrections.refined)
                elif isinstance(msg, PlacesMessage) and self.session.frontend.places is not None:
                    for indexed in msg.indexed:
                        self.session.frontend.places.take(indexed)
            msg = _get(self.ch.to_tracker, 0.0)

    def _wait_for_map(self) -> None:
        """Frame 1 onwards need the warmed-up map of frame 0."""
        if self.map is None:
            self.cores.busy(False)  # the mapper has the machine for the warm-up
        while self.map is None:
            self._interruptible()

    def _wait_for_mapper(self, lag: int) -> None:
        """Offline: track against a map at most `lag` keyframes behind (the mapper has the machine meanwhile)."""
        if self.ch.board.unmapped_keyframes() <= lag:
            return
        self.cores.busy(False)
        while self.ch.board.unmapped_keyframes() > lag:
            self._interruptible()

    def _interruptible(self) -> None:
        """One poll of a wait that a stop, an exit or a reset ends."""
        if self.ch.control.stopping or self.ch.control.exiting or self.ch.control.epoch != self.epoch:
            raise Interrupted
        self._receive(POLL_S)
        self.cores.update()

    def _catch_up(self) -> bool:
        """Offline, a view that left the map waits for every keyframe made so far to be mapped: the tracker can be
        `max_keyframe_lag` keyframes ahead of the map, and a camera walking into new space (2.5 cm a frame on the
        synthetic long room) then meets space that only those keyframes saw. Whether it is lost then depended on
        how far the mapper had got. True when the map moved on."""
        if self.ch.board.unmapped_keyframes() == 0:
            return False
        version = self.map_version
        with self.ch.board.timed(Counter.TRACK_WAIT_S):
            self._wait_for_mapper(0)
            while self.map.superseded():  # a grown map: its MapAttach was sent before the step counted as done
                self._interruptible()
        self._refresh_map()
        self.cores.busy(True)
        return self.map_version != version

    def _refresh_map(self) -> None:
        version = self.replica.refresh(self.map, self.map_version)
        if version is not None:
            self.replica.observed.mapped(self.map.mapped)
            log.debug("tracker: map version %d (%.1f ms to copy in)", version, 1000 * self.map.read_seconds)
            self.map_version = version
            self.ch.board.add(Counter.READ_SECONDS, self.map.read_seconds)
            self.ch.board.add(Counter.READS)

    def _track(self, item) -> None:
        self.faults.check("tracker", self.tracked)
        pf = None
        if self.live and self.replica.started and self.map is None:
            pf = self._prepare(item)
            if self._dead_reckon(pf, item.arrival):
                return
        if self.replica.started:
            with self.ch.board.timed(Counter.TRACK_WAIT_S):
                self._wait_for_map()
                if not self.live and self.cfg.runtime.max_keyframe_lag is not None:
                    self._wait_for_mapper(self.cfg.runtime.max_keyframe_lag)
            self._refresh_map()
        self.cores.busy(True)
        start = time.monotonic()
        board = self.ch.board
        pf = pf or self._prepare(item)
        if not self.replica.started:  # the first frame starts the map; the mapper warms it up
            tracked, kf = self.session.first(pf)
            self.replica.start(tracked.extent)
            self._hand_over(kf, tracked.extent)
        else:
            with board.timed(Counter.TRACK_ALIGN_S):
                tracked = self.session.step(pf, self.replica, None if self.live else self._catch_up)
        self._report(tracked, item.arrival, start)
        if tracked.keyframe_due:  # after the pose is out: it need not wait for the keyframe
            with board.timed(Counter.TRACK_KEYFRAME_S):
                kf = self.session.new_keyframe(pf, tracked)
                self._hand_over(kf, None)  # (the mapper indexes it for relocalization: PlacesMessage)
        if self.localizing and tracked.pose is not None:
            self._follow(tracked.pose)
        self.tracked += 1
        board.add(Counter.TRACKED)
        board.set(Counter.TRACKED_INDEX, pf.index)
        board.set(Counter.TRACKED_STAMP, pf.timestamp)
        board.set(Counter.TRACKER_PEAK_MB, peak_rss_mb())
        board.set(Counter.TRACKER_DEVICE_PEAK_MB, device_peak_mb(self.replica.device))

    def _follow(self, pose: TrackedPose) -> None:
        """Localization makes no keyframe that would take the mapper to the next submap: the tracker tells it where
        the camera is, every FOLLOW_EVERY frames and at once when a keyframe's features found it, and the mapper
        attaches it to the submap the camera is in (Atlas.follow)."""
        found = pose.relocalized_from
        if (pose.lost and found is None) or (found is None and self.tracked - self.asked_at < FOLLOW_EVERY):
            return
        self.asked_at = self.tracked
        self.ch.to_mapper.put(CameraAt(self.epoch, pose.pose.double().numpy()[:3, 3], found))

    def _prepare(self, item) -> PreparedFrame:
        with self.ch.board.timed(Counter.TRACK_PREPARE_S):
            return prepare_frame(Frame(item.index, item.timestamp, item.rgb, item.depth, item.gt_pose,
                                       item.odom_pose), self.intr, self.cfg.camera)

    def _dead_reckon(self, pf: PreparedFrame, arrival: float) -> bool:
        """Live, before the first map: the frame's pose from the odometry alone (TrackingSession.dead_reckon)
        instead of waiting for the warm-up while the camera's frames are dropped. False where the odometry cannot
        pose it: the frame then waits for the map."""
        self.cores.busy(True)
        start = time.monotonic()
        board = self.ch.board
        with board.timed(Counter.TRACK_ALIGN_S):
            reckoned = self.session.dead_reckon(pf)
        if reckoned is None:
            return False
        self._report(reckoned, arrival, start)
        self.tracked += 1
        board.add(Counter.TRACKED)
        return True

    def _report(self, tracked: Tracked, arrival: float, start: float) -> None:
        record = tracked.record
        done = time.monotonic()
        log.debug("tracker: frame %d tracked in %.2f s (%d threads)", record.index, done - start,
                  torch.get_num_threads())
        with self.ch.board.timed(Counter.TRACK_REPORT_S):
            self.ch.to_parent.put(TrackedFrame(self.epoch, record, tracked.anchor, done - arrival, done))

    def _hand_over(self, kf: Keyframe, extent: Optional[np.ndarray]) -> None:
        """Send a new keyframe to the mapper; keep only the newest one's images here."""
        self.replica.add_keyframe(kf)
        self.ch.to_mapper.put(KeyframeMessage.of(self.epoch, kf, extent))
        self.ch.board.add(Counter.KEYFRAMES)

    def _finish(self) -> None:
        trajectory = self.session.trajectory
        done = TrackerFinished(self.epoch, len(trajectory), trajectory.keyframes)
        self.ch.to_mapper.put(done)
        self.ch.to_parent.put(done)
        self.finished = True
        self.cores.busy(False)


def tracker_main(setup: WorkerSetup, channels: Channels, errors) -> None:
    run_worker("tracker", lambda: TrackerWorker(setup, channels).run(), setup, errors)


# -------------------------------------------------------------------------------------------------------- mapper

class MapperWorker:
    def __init__(self, setup: WorkerSetup, ch: Channels):
        self.setup = setup
        self.ch = ch
        self.live = setup.policy == "live"
        self.faults = FaultPlan.parse(setup.faults)
        self.cfg, self.intr = working_setup(setup.cfg, setup.intrinsics)
        self.dirs_cam = pixel_directions_table(self.intr)
        self.epoch = ch.control.epoch
        self.early: list = []  # messages of an epoch this worker has not caught up with yet (see _receive)
        self.steps = 0  # mapping steps done (the warm-up is step 0), over all epochs
        self._new_state()
        self.publishing_mid_step = False
        self.first_map_at: Optional[int] = None  # the warm-up iteration that attaches the tracker, if not its end
        self.cores = CoreShare(ch.board, Counter.MAPPER_BUSY, Counter.TRACKER_BUSY, Counter.MAPPER_BEAT,
                               setup.threads, setup.cfg.runtime.lend_threads)
        self.budget = MappingBudget.of(self.cfg.mapping.iterations, self.live, self.cfg.runtime.idle_iterations,
                                       self.cfg.runtime.catch_up_iterations, self.cfg.runtime.keyframe_backlog)
        import_optimiser_code()

    def _new_state(self) -> None:
        self.atlas: Optional[Atlas] = None  # the submaps (one, with submaps.radius_m 0); None before keyframe 0
        self.pending: deque = deque()  # keyframes received, not yet mapped
        self.map: Optional[SharedMap] = None
        self.steps_in_epoch = 0
        self.mapping = False  # a step is in progress (counts as backlog: the keyframe is not mapped yet)
        self.tracker_done = False
        self.tracker_attached = False  # told of the map (MapAttach) in this epoch
        self.finished = False
        # The keyframes for relocalization, indexed here and sent to the tracker's replica (places.py): a live
        # tracker that extracted their features and checked the map with them while frames waited dropped frames.
        cfg = self.cfg
        self.places = KeyframePlaces(cfg.relocalization, self.intr, cfg.run.seed, publish=True,
                                     keep_checks=cfg.submaps.radius_m > 0 and cfg.submaps.loop_closure) \
            if cfg.relocalization.enabled and cfg.tracking.mode == "track" else None
        self.attached_submap: Optional[int] = None  # the submap the tracker was last attached to
        self.camera_at: Optional[CameraAt] = None  # localization: where the tracker says the camera is
        if self.epoch == 0 and self.setup.checkpoint:
            self.atlas = loaded_slam(self.setup.checkpoint, self.setup.cfg, self.setup.intrinsics).atlas
            if self.places is not None:
                self.places.start_lost(self.atlas.world_keyframes())
            self.map = SharedMap.create(self.ch.map_meta, self.scene.field)
            self.steps_in_epoch = 1
            self._publish()
            self._attach_tracker()

    @property
    def scene(self) -> Optional[SceneMap]:
        """The active submap (the map, with one)."""
        return None if self.atlas is None else self.atlas.active

    def run(self) -> None:
        self.ch.to_parent.put(WorkerReady("mapper", os.getpid()))
        memory, collections = PeriodicRelease(), started_up()
        while not self.ch.control.exiting:
            self.cores.update()
            memory.release()
            self.ch.board.set(Counter.MAP_GC_S, collections.seconds)
            self._sync_epoch()
            self._serve_requests()
            self._receive(0.0 if self.pending else POLL_S)
            self._follow_camera()
            if not self.pending:
                self.cores.busy(False)
            if self.pending and not self.ch.control.stopping:
                try:
                    self._map_next()
                except Interrupted:
                    pass
                self._index_places()
            elif self.places is not None and self.places.idle_work:
                self._index_places()
            elif self.tracker_done and not self.finished:
                self.ch.to_parent.put(MapperFinished(self.epoch))
                self.finished = True

    def _sync_epoch(self) -> None:
        """Catch up with a reset: forget the map, then take the new epoch's messages that came early."""
        epoch = self.ch.control.epoch
        if epoch != self.epoch:
            self.epoch = epoch
            self._new_state()
            early, self.early = self.early, []
            for msg in early:
                if msg.epoch == epoch:  # (after two quick resets, the first one's messages are moot)
                    self._accept(msg)
            self._update_backlog()

    def _receive(self, timeout: float) -> None:
        msg = _get(self.ch.to_mapper, timeout)
        while msg is not None:
            if isinstance(msg, KeyframeMessage):
                self.ch.board.add(Counter.KEYFRAMES_RECEIVED)  # off the queue, even if it is from before a reset
            # After a reset the tracker may start the new map while this worker is still in the old epoch (e.g.
            # idle in this very call): keep such messages for _sync_epoch. Older epochs' messages are dropped.
            if msg.epoch > self.epoch:
                self.early.append(msg)
            elif msg.epoch == self.epoch:
                self._accept(msg)
            msg = _get(self.ch.to_mapper, 0.0)
        self._update_backlog()

    def _accept(self, msg) -> None:
        if isinstance(msg, KeyframeMessage):
            self.pending.append(msg)
        elif isinstance(msg, CameraAt):
            self.camera_at = msg
        elif isinstance(msg, TrackerFinished):
            self.tracker_done = True

    def _update_backlog(self) -> None:
        self.ch.board.set(Counter.KEYFRAME_BACKLOG, len(self.pending) + int(self.mapping))

    def _keyframe_count(self) -> int:
        """Keyframes received so far, mapped or waiting (the tracker numbers them 0, 1, ...)."""
        if self.atlas is None:
            made = 0
        elif len(self.atlas.submaps) == 1:
            made = self.scene.keyframes.made
        else:  # (a submap's store counts its own, shared ones included)
            made = max(self.atlas.owner) + 1
        return made + len(self.pending)

    # ------------------------------------------------------------------------------------------- mapping steps
    def _map_next(self) -> None:
        self.faults.check("mapper", self.steps)
        self.cores.busy(True)
        self.mapping = True
        try:
            self._map_next_keyframe()
        finally:
            self.mapping = False
            self._update_backlog()

    def _map_next_keyframe(self) -> None:
        start = time.perf_counter()
        if self.scene is None:
            refined, loss = {}, self._start_map(self.pending.popleft())
            attach = not self.tracker_attached
        else:
            field, began = self.scene.field, set()
            with self.ch.board.timed(Counter.MAP_ADD_S):
                for _ in range(self.budget.merged(len(self.pending)) + 1):  # behind: into the newest one's window
                    sub, new = self.atlas.place(self._indexed(self.pending.popleft().keyframe()))
                    if new:
                        began.add(sub.number)
            self._update_backlog()
            # Grown, or (submaps) another submap: a new map, in new shared buffers.
            attach = self.scene.field is not field
            if attach:
                self.map = SharedMap.create(self.ch.map_meta, self.scene.field)
            with self.ch.board.timed(Counter.MAP_STEP_S):
                if self.scene.number in began:  # a submap begun: warmed up as the first map was
                    step = self._step(lambda: self.scene.warm_up(self._after_iteration))
                else:
                    step = self._step(lambda: self.scene.map_newest(self._after_regular_iteration,
                                                                    self.budget.step_iterations()))
            loss, refined = (step.loss, {i: p.numpy().copy() for i, p in
                                         self.atlas.to_world(self.scene, step.refined).items()}) if step else \
                (float("nan"), {})
        version = self._publish()
        log.debug("mapper: step %d done in %.2f s (%d threads at the end), map version %d", self.steps,
                  time.perf_counter() - start, torch.get_num_threads(), version)
        if attach:
            self._attach_tracker()
        dropped = [n for n in self.scene.keyframes.take_dropped() if self.atlas.owns(self.scene, n)]
        if refined or dropped:
            self.ch.to_tracker.put(Corrections(self.epoch, PoseCorrections(refined, tuple(dropped))))
            if self.places is not None:
                self.places.refine(refined)
                self.places.forget(dropped)
        self.steps_in_epoch += 1
        self.steps += 1
        board = self.ch.board
        board.add(Counter.MAPPING_STEPS)
        board.set(Counter.MAPPER_PEAK_MB, peak_rss_mb())
        board.set(Counter.MAPPER_DEVICE_PEAK_MB, device_peak_mb(self.scene.device))
        board.set(Counter.POINTS_OUTSIDE, sum(sub.points_outside for sub in self.atlas.submaps))
        board.set(Counter.POINTS_SEEN, sum(sub.points_seen for sub in self.atlas.submaps))
        with board.timed(Counter.MAP_MEASURE_S):
            memory = self.atlas.memory()  # (summed over the submaps)
            consistency = self.scene.consistency() if self.scene.consistency_due() else None
        board.set(Counter.MAP_BYTES, memory["map_bytes"])
        board.set(Counter.KEYFRAME_BYTES, memory["keyframe_bytes"])
        board.set(Counter.KEYFRAMES_KEPT, memory["keyframes_kept"])
        board.set(Counter.SUBMAPS, memory["submaps"])
        board.set(Counter.LOOPS_CLOSED, memory["loops_closed"])
        if consistency is not None:
            board.set(Counter.CONSISTENCY_MM, consistency.median_mm)
            board.set(Counter.CONSISTENCY_AGREE, consistency.agree_fraction)
            board.set(Counter.CONSISTENCY_PAIRS, consistency.pairs)
        self.ch.to_parent.put(MappingReport(self.epoch, self.steps, version, loss, time.perf_counter() - start,
                                            time.monotonic(), refined))

    def _start_map(self, msg: KeyframeMessage) -> float:
        """The map of the first keyframe, over the extent the tracker chose, and its warm-up."""
        self._update_backlog()
        self.atlas = Atlas(self.cfg, self.intr, self.dirs_cam)
        self.atlas.new_submap(None)
        self.scene.start(msg.extent)
        self.scene.add_keyframe(self.atlas.local(self.scene, self._indexed(msg.keyframe())))
        self.map = SharedMap.create(self.ch.map_meta, self.scene.field)
        self.first_map_at = self.cfg.runtime.first_map_after
        try:
            step = self._step(lambda: self.scene.warm_up(self._after_iteration), publish=False)
        finally:
            self.first_map_at = None
        return step.loss if step else float("nan")

    def _indexed(self, kf: Keyframe) -> Keyframe:
        """A new keyframe (world pose), for relocalization and the map check too."""
        if self.places is not None:
            self.places.remember(kf)
        return kf

    def _index_places(self) -> None:
        """Index the new keyframes and check the map with them (one keyframe, at most 45 ms: between two
        steps), and send the tracker what was indexed."""
        if self.places is None:
            return
        board = self.ch.board
        with board.timed(Counter.MAP_INDEX_S):
            while self.places.index_next():
                pass
        done = self.places.take_done()
        if done:
            self.ch.to_tracker.put(PlacesMessage(self.epoch, done))
        self._close_loops()
        check = self.places.check
        if check is not None:
            board.set(Counter.MAP_CHECK_CM, 100.0 * check.metres)
            board.set(Counter.MAP_CHECK, 2.0 if check.disagrees else 1.0)

    def _close_loops(self) -> None:
        """Keyframes placed by another submap's keyframes (loops, submaps/atlas.py): the graph solved, the moved
        keyframes' poses sent to the tracker (after the active submap's new anchor) and to the parent."""
        refined, board = {}, self.ch.board
        for check in self.places.take_checks():  # (the frame the tracker is at is the first to see the correction)
            refined.update(self.atlas.close_loop(check, int(board.get(Counter.TRACKED_INDEX)),
                                                 board.get(Counter.TRACKED_STAMP)))
        if not refined:
            return
        refined = {n: p.numpy().copy() for n, p in refined.items()}
        self._publish()  # a new map version: the mesh follows the moved submaps
        self._attach_tracker()
        self.ch.to_tracker.put(Corrections(self.epoch, PoseCorrections(refined, ())))
        self.places.refine(refined)
        self.ch.to_parent.put(LoopClosed(self.epoch, refined))
        board.set(Counter.LOOPS_CLOSED, self.atlas.loops)
        board.set(Counter.LOOP_CORRECTION_S, self.atlas.closures[-1].seconds)

    def _follow_camera(self) -> None:
        """Localization: attach the tracker to the submap the camera is in (Atlas.follow), if another."""
        if self.camera_at is None or self.atlas is None:
            return
        at, self.camera_at = self.camera_at, None
        if self.atlas.follow(at.position, at.found_by).number != self.attached_submap:
            self.map = SharedMap.create(self.ch.map_meta, self.scene.field)
            self._publish()
            self._attach_tracker()

    def _attach_tracker(self) -> None:
        """Tell the tracker where the map is; with submaps, the active one's anchor, and its observed space when
        the tracker was attached to another."""
        sub = self.scene
        changed = sub.number != self.attached_submap and self.cfg.submaps.radius_m > 0
        self.ch.to_tracker.put(MapAttach(self.epoch, self.map.buffers, self.map.generation, sub.extent, sub.number,
                                         sub.anchor, copy.deepcopy(sub.observed) if changed else None,
                                         max((kf.number for kf in sub.keyframes), default=-1)))
        self.attached_submap = sub.number
        self.tracker_attached = True

    def _step(self, run, publish: bool = True):
        self.publishing_mid_step = publish
        try:
            return run()
        except Interrupted:
            if self.ch.control.epoch != self.epoch or self.ch.control.exiting:
                raise
            return None  # stopping: keep the map as it is after the last completed iteration
        finally:
            self.publishing_mid_step = False

    def _after_regular_iteration(self, iterations: int) -> bool:
        return self._after_iteration(iterations) or self.budget.stop_early(iterations, self.keyframes_waiting())

    def keyframes_waiting(self) -> int:
        """Keyframes newer than the one being mapped: received, or still in the queue."""
        queued = self.ch.board.get(Counter.KEYFRAMES) - self.ch.board.get(Counter.KEYFRAMES_RECEIVED)
        return len(self.pending) + int(queued)

    def _publish(self, step_done: bool = True) -> int:
        # In the middle of a step the newest keyframe is not fitted yet.
        mapped = self.scene.keyframes.made - (0 if step_done else 1)
        version = self.map.publish(self.scene.field, mapped)
        self.ch.board.add(Counter.PUBLISH_SECONDS, self.map.publish_seconds)
        self.ch.board.add(Counter.PUBLISHES)
        return version

    def _after_iteration(self, iterations: int) -> bool:
        """After every iteration of a mapping step (`iterations` done): abandon it for a stop or a reset, lend or
        take back cores, publish, serve requests. Never ends the step itself (that is the budget's call)."""
        control = self.ch.control
        if control.stopping or control.exiting or control.epoch != self.epoch:
            raise Interrupted
        self.cores.update()
        every = self.cfg.runtime.publish_every
        if self.publishing_mid_step and every and iterations % every == 0:
            self._publish(step_done=False)
        if iterations == self.first_map_at:  # the warm-up's keyframe counts as mapped from here on
            self._publish()
            self._attach_tracker()
        self._serve_requests()
        return False

    # ---------------------------------------------------------------------------------------------- snapshots
    def _serve_requests(self) -> None:
        req = _get(self.ch.commands, 0.0)
        while req is not None:
            answer = self._mesh_snapshot(req) if isinstance(req, MeshRequest) else self._snapshot(req)
            self.ch.answers.put(MapperSnapshot(req.request_id, self.epoch, answer))
            req = _get(self.ch.commands, 0.0)

    def _mesh_snapshot(self, req: MeshRequest):
        """The map for the mesh process, made here: the parent only passes it on (a whole `_snapshot` of the
        state took the node 1-3 s per mesh on 2 cores, and stalled its poses)."""
        if req.epoch != self.epoch or self.scene is None:
            return None
        return PackedSnapshot.of(snapshot_for_meshing(self.atlas, req.have))

    def _snapshot(self, req: SnapshotRequest) -> Optional[str | bytes]:
        """The scene map (field, keyframes, window sampler): what a `SLAM` checkpoint needs besides the
        trajectory, once it holds the `min_keyframes` the parent has seen."""
        if req.epoch != self.epoch or (req.min_keyframes == 0 and self.scene is None):
            return None
        while self._keyframe_count() < req.min_keyframes:  # keyframes still in flight from the tracker
            if self.ch.control.exiting or self.ch.control.epoch != self.epoch:
                return None  # moot: reset or exit
            self._receive(POLL_S)
            self.cores.update()
        if self.scene is None:  # asked before the warm-up started: a map that is still random
            first = self.pending[0]
            scene = SceneMap(self.cfg, self.intr, self.dirs_cam)
            scene.start(first.extent)
            scene.add_keyframe(first.keyframe())
            state = scene.state_dict()
        elif self.cfg.submaps.radius_m > 0:
            state = self._atlas_state(req.min_keyframes)
        else:
            state = self.scene.state_dict()
        if "atlas" not in state:
            for msg in self.pending:  # received, not mapped yet: keyframes of the map all the same
                if msg.number >= state["keyframes_made"]:
                    state["keyframes"].append(dict(msg.keyframe().__dict__))
                    state["keyframes_made"] = msg.number + 1
            if req.min_keyframes:  # the parent's trajectory knows the first ones: a checkpoint holds those, not newer
                state["keyframes"] = [kf for kf in state["keyframes"] if kf["number"] < req.min_keyframes]
                state["keyframes_made"] = min(state["keyframes_made"], req.min_keyframes)
        # A file in shared memory: the bytes through the queue cost five copies and a pipe (0.8 s for the 55 MB of
        # a 300-frame ICL map, at the end of every offline run); a file costs one write and one read.
        if req.path:
            try:
                with atomic_output(req.path, fsync=False) as tmp:  # nothing to keep across a crash: no fsync
                    torch.save(state, tmp)
                return req.path
            except (OSError, RuntimeError) as e:  # e.g. a small /dev/shm; atomic_output removed the partial file
                log.debug("mapper: snapshot file %s not written (%s); sending the bytes", req.path, e)
        buf = io.BytesIO()
        torch.save(state, buf)
        return buf.getvalue()

    def _atlas_state(self, min_keyframes: int) -> dict:
        """The submaps and their pose graph (Atlas.state_dict) as a snapshot: the keyframes received and not mapped
        yet in the active submap (its frame), and with `min_keyframes` only the keyframes the parent has seen."""
        atlas = self.atlas.state_dict()
        active = next(saved["map"] for saved in atlas["submaps"] if saved["number"] == self.scene.number)
        to_local = np.linalg.inv(Atlas.anchor(self.scene))
        for msg in self.pending:
            kf = msg.keyframe().moved(to_local)
            active["keyframes"].append(dict(kf.__dict__))
            atlas["owner"][kf.number] = self.scene.number
        if min_keyframes:
            for saved in atlas["submaps"]:
                saved["map"]["keyframes"] = [kf for kf in saved["map"]["keyframes"] if kf["number"] < min_keyframes]
            atlas["owner"] = {n: sub for n, sub in atlas["owner"].items() if n < min_keyframes}
        return {"atlas": atlas}


def mapper_main(setup: WorkerSetup, channels: Channels, errors) -> None:
    def body():
        lower_priority(setup.cfg.runtime.mapper_nice)
        MapperWorker(setup, channels).run()

    run_worker("mapper", body, setup, errors)
