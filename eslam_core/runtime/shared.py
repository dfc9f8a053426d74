"""What the parent, the tracker and the mapper share in memory: the frame ring, the map, counters and flags.

Everything here lives in torch tensors moved to shared memory (`share_memory_()`). With torch's default
`file_descriptor` sharing strategy a segment is unlinked from /dev/shm as soon as it is created and lives only as
long as some process maps it, so nothing is left behind even when every process is killed. The locks and
conditions are multiprocessing ones (named POSIX semaphores, unlinked when the parent drops them, or by
multiprocessing's resource tracker if the parent is killed).

- `FrameRing`: frames from the parent to the tracker, without pickling images. A bounded ring of slots (uint8
  colour, float32 depth at the working resolution) with index, timestamp, ground-truth pose and arrival time.
  Slots are written outside the lock (a slot being written is never pending, so no reader looks at it) and copied
  out under it (a copy is well under a millisecond; a reader never sees a slot the writer is reusing).
- `SharedMap`: the map's parameters from the mapper to the tracker. Double buffered: the mapper writes the buffer
  that is not the newest, then flips `front` and bumps `version` under a short lock; the tracker pins the front
  buffer while it copies it into its own field. A buffer is only rewritten once nobody has it pinned, so a reader
  never sees a half-written map, and neither side waits for the other's copy (only, rarely, for a slow reader to
  let go of the older buffer). Costs are counted in the health board (`Health.map_publish_ms/map_read_ms`).
- `HealthBoard`: counters, each written by one process only (so no lock), read by the parent for `health()`.
- `Control`: flags from the parent to the workers (stop now, exit, epoch = number of resets).
"""
from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass
from enum import IntEnum
from typing import Optional

import numpy as np
import torch
from torch import nn

from eslam_core.device import synchronize
from eslam_core.runtime.api import frames_to_skip


class SharedMemoryError(RuntimeError):
    """The shared map does not fit the field it is copied into (the two workers built different maps)."""


# ---------------------------------------------------------------------------------------------------- frame ring

@dataclass
class RingFrame:
    """A frame copied out of the ring (tensors owned by the reader)."""

    index: int
    timestamp: float
    rgb: np.ndarray  # (H, W, 3) uint8, working resolution
    depth: np.ndarray  # (H, W) float32 metres
    gt_pose: Optional[np.ndarray]
    arrival: float  # time.monotonic() at submit (the clock is the same in every process)
    odom_pose: Optional[np.ndarray] = None  # see Frame.odom_pose


class FrameRing:
    WRITTEN, TAKEN, CLOSED = 0, 1, 2  # positions in `counts`: frames ever written / taken (or dropped), input closed

    def __init__(self, capacity: int, height: int, width: int, ctx):
        if capacity < 1:
            raise ValueError(f"the frame buffer needs at least one slot, got {capacity}")
        self.capacity = capacity
        self.rgb = torch.zeros(capacity, height, width, 3, dtype=torch.uint8).share_memory_()
        self.depth = torch.zeros(capacity, height, width, dtype=torch.float32).share_memory_()
        self.index = torch.zeros(capacity, dtype=torch.int64).share_memory_()
        self.stamps = torch.zeros(capacity, 2, dtype=torch.float64).share_memory_()  # timestamp, arrival
        self.gt_pose = torch.zeros(capacity, 4, 4, dtype=torch.float64).share_memory_()
        self.has_pose = torch.zeros(capacity, dtype=torch.bool).share_memory_()
        self.odom_pose = torch.zeros(capacity, 4, 4, dtype=torch.float64).share_memory_()
        self.has_odom = torch.zeros(capacity, dtype=torch.bool).share_memory_()
        self.counts = torch.zeros(3, dtype=torch.int64).share_memory_()
        self.cond = ctx.Condition(ctx.Lock())

    def _pending(self) -> int:
        return int(self.counts[self.WRITTEN] - self.counts[self.TAKEN])

    def pending(self) -> int:
        """Frames written and not yet taken (read without the lock: a snapshot for health figures)."""
        return max(0, self._pending())

    def put(self, rgb: np.ndarray, depth: np.ndarray, index: int, timestamp: float, gt_pose: Optional[np.ndarray],
            arrival: float, live: bool, timeout: float, odom_pose: Optional[np.ndarray] = None) -> tuple[bool, int]:
        """Write one frame (single writer). Returns (written, evicted).

        Offline (live=False): waits up to `timeout` s for a free slot and returns (False, 0) without one, so that the
        caller can check on the workers between waits. Live: never waits; a full ring loses its oldest pending frame.
        """
        evicted = 0
        with self.cond:
            if self._pending() >= self.capacity:
                if live:
                    self.counts[self.TAKEN] += 1
                    evicted = 1
                elif not self.cond.wait_for(lambda: self._pending() < self.capacity, timeout):
                    return False, 0
            slot = int(self.counts[self.WRITTEN]) % self.capacity
        # The slot is not pending, so the reader never looks at it while it is written. (Numpy copies: torch's
        # would spread over threads that wait for cores the workers hold, 3 ms per image on 2 cores.)
        np.copyto(self.rgb[slot].numpy(), rgb)
        np.copyto(self.depth[slot].numpy(), depth)
        self.index[slot] = index
        self.stamps[slot, 0] = timestamp
        self.stamps[slot, 1] = arrival
        self.has_pose[slot] = gt_pose is not None
        if gt_pose is not None:
            np.copyto(self.gt_pose[slot].numpy(), gt_pose)
        self.has_odom[slot] = odom_pose is not None
        if odom_pose is not None:
            np.copyto(self.odom_pose[slot].numpy(), odom_pose)
        with self.cond:
            self.counts[self.WRITTEN] += 1
            self.cond.notify_all()
        return True, evicted

    def take(self, live: bool, timeout: float, backlog: int = 0) -> tuple[Optional[RingFrame], int]:
        """The next frame (offline: the oldest pending; live: see api.frames_to_skip) and how many frames were
        skipped; (None, 0) when nothing arrived within `timeout` s or the input is closed and empty."""
        with self.cond:
            if not self.cond.wait_for(lambda: self._pending() > 0 or bool(self.counts[self.CLOSED]), timeout):
                return None, 0
            pending = self._pending()
            if pending <= 0:
                return None, 0
            skipped = frames_to_skip(pending, live, backlog)
            taken = int(self.counts[self.TAKEN]) + skipped
            slot = taken % self.capacity
            frame = RingFrame(
                int(self.index[slot]), float(self.stamps[slot, 0]), self.rgb[slot].numpy().copy(),
                self.depth[slot].numpy().copy(), self.gt_pose[slot].numpy().copy() if bool(self.has_pose[slot]) else
                None, float(self.stamps[slot, 1]),
                self.odom_pose[slot].numpy().copy() if bool(self.has_odom[slot]) else None)
            self.counts[self.TAKEN] = taken + 1
            self.cond.notify_all()
        return frame, skipped

    def close_input(self) -> None:
        """No more frames will come: the reader finishes what is pending, then sees the ring as drained."""
        with self.cond:
            self.counts[self.CLOSED] = 1
            self.cond.notify_all()

    def drained(self) -> bool:
        return bool(self.counts[self.CLOSED]) and self._pending() <= 0

    def discard_pending(self) -> int:
        """Drop every pending frame (on stop or reset); returns how many."""
        with self.cond:
            n = max(0, self._pending())
            self.counts[self.TAKEN] = self.counts[self.WRITTEN]
            self.cond.notify_all()
        return n


# ------------------------------------------------------------------------------------------------------ the map

class MapMeta:
    """The part of the shared map that exists before the map does (created by the parent, inherited at spawn)."""

    # PINS, PINS + 1: readers holding buffer 0 / 1; MAPPED: how many keyframes the newest map is fitted to;
    # GENERATION: how many buffer pairs the mapper has made (a grown map gets new buffers of its new size).
    VERSION, FRONT, PINS, MAPPED, GENERATION = 0, 1, 2, 4, 5

    def __init__(self, ctx):
        self.lock = ctx.Lock()
        self.state = torch.tensor([0, -1, 0, 0, 0, 0], dtype=torch.int64).share_memory_()

    @property
    def version(self) -> int:
        return int(self.state[self.VERSION])


def parameter_layout(field: nn.Module) -> list[tuple[nn.Parameter, int, int]]:
    """(parameter, offset, size) of every parameter in one flat vector, in registration order (the same in any
    process that builds the field from the same bound and config)."""
    layout, offset = [], 0
    for p in field.parameters():
        layout.append((p, offset, p.numel()))
        offset += p.numel()
    return layout


class SharedMap:
    """The mapper's field in a pair of shared buffers: the mapper writes the back one and flips; readers copy the
    front one out under a pin. A map that grows gets a new pair (a new generation): a reader still attached to the
    old pair reads nothing more from it, never a half-written or differently sized map, until it attaches to the
    new pair (MapAttach)."""

    def __init__(self, meta: MapMeta, buffers: torch.Tensor, generation: int):
        self.meta = meta
        self.buffers = buffers  # (2, P) float32 in shared memory
        self.generation = generation
        self.publish_seconds = 0.0
        self.read_seconds = 0.0
        self.mapped = 0  # of the map last read: how many keyframes (the first ones) it has been fitted to

    @staticmethod
    def create(meta: MapMeta, field: nn.Module) -> "SharedMap":
        """Buffers sized for `field` (by its owner, the mapper); nothing is readable until the first publish.
        They live on the field's device: shared memory for a CPU map; for a GPU map device memory, which the
        torch.multiprocessing queue hands to the tracker by CUDA IPC (the mapper holds the buffers while they are
        the newest generation; torch keeps them for a reader that still holds them after that)."""
        size = sum(p.numel() for p in field.parameters())
        device = next(field.parameters()).device
        buffers = torch.zeros(2, size, dtype=torch.float32, device=device)
        if device.type == "cpu":
            buffers.share_memory_()
        with meta.lock:  # pins stay: a reader of the old pair may hold one, and publish waits for it
            meta.state[MapMeta.FRONT] = -1
            meta.state[MapMeta.GENERATION] += 1
            generation = int(meta.state[MapMeta.GENERATION])
        return SharedMap(meta, buffers, generation)

    def _check(self, layout: list) -> None:
        size = sum(n for _, _, n in layout)
        if size != self.buffers.shape[1]:
            raise SharedMemoryError(f"the shared map holds {self.buffers.shape[1]} values but the field has {size}: "
                                    f"tracker and mapper built different maps (same config and bound expected)")

    def publish(self, field: nn.Module, mapped: int) -> int:
        """Make the field's current parameters the newest map, fitted to the first `mapped` keyframes; returns the
        new version."""
        start = time.perf_counter()
        layout = parameter_layout(field)
        self._check(layout)
        while True:
            with self.meta.lock:
                front = int(self.meta.state[MapMeta.FRONT])
                back = 1 if front == 0 else 0
                if int(self.meta.state[MapMeta.PINS + back]) == 0:
                    break
            time.sleep(0.0005)  # a reader still copies the older map out of that buffer
        buffer = self.buffers[back]
        with torch.no_grad():
            for p, offset, n in layout:
                buffer[offset: offset + n].copy_(p.detach().reshape(-1))
        synchronize(buffer.device)  # a GPU's copies are queued: done before another process may read them
        with self.meta.lock:
            self.meta.state[MapMeta.FRONT] = back
            self.meta.state[MapMeta.MAPPED] = mapped
            self.meta.state[MapMeta.VERSION] += 1
            version = int(self.meta.state[MapMeta.VERSION])
        self.publish_seconds = time.perf_counter() - start
        return version

    def superseded(self) -> bool:
        """Whether the mapper has made a newer generation (a grown map) than this one."""
        with self.meta.lock:
            return int(self.meta.state[MapMeta.GENERATION]) != self.generation

    def read_into(self, field: nn.Module, have_version: int) -> Optional[int]:
        """Copy the newest map into `field` if it is newer than `have_version`; returns its version, or None when
        there is nothing newer (or nothing published yet)."""
        start = time.perf_counter()
        with self.meta.lock:
            front = int(self.meta.state[MapMeta.FRONT])
            version = int(self.meta.state[MapMeta.VERSION])
            if front < 0 or version == have_version or int(self.meta.state[MapMeta.GENERATION]) != self.generation:
                return None
            self.mapped = int(self.meta.state[MapMeta.MAPPED])
            self.meta.state[MapMeta.PINS + front] += 1
        try:
            layout = parameter_layout(field)
            self._check(layout)
            buffer = self.buffers[front]
            with torch.no_grad():
                for p, offset, n in layout:
                    p.copy_(buffer[offset: offset + n].view_as(p))
            synchronize(buffer.device)  # copied out before the pin goes and the mapper may rewrite the buffer
        finally:
            with self.meta.lock:
                self.meta.state[MapMeta.PINS + front] -= 1
        self.read_seconds = time.perf_counter() - start
        return version


# ------------------------------------------------------------------------------------------- counters and flags

class Counter(IntEnum):
    RECEIVED = 0  # parent
    DROPPED_AT_SUBMIT = 1  # parent: evicted from a full ring (live), discarded at stop or reset
    DROPPED_BY_TRACKER = 2  # tracker: skipped to a newer frame (live)
    TRACKED = 3  # tracker
    KEYFRAMES = 4  # tracker: keyframes made (and handed to the mapper)
    KEYFRAMES_RECEIVED = 5  # mapper: keyframes taken off its queue
    KEYFRAME_BACKLOG = 6  # mapper: received and not yet mapped
    MAPPING_STEPS = 7  # mapper
    PUBLISH_SECONDS = 8  # mapper: total time spent publishing the map
    PUBLISHES = 9  # mapper
    READ_SECONDS = 10  # tracker: total time spent copying the map in
    READS = 11  # tracker
    POINTS_OUTSIDE = 12  # mapper: keyframe depth points the map could not cover (SceneMap.points_outside)
    POINTS_SEEN = 13  # mapper
    TRACKER_PEAK_MB = 14
    MAPPER_PEAK_MB = 15
    TRACKER_BUSY = 16  # tracker: 1 while it has a frame to track (0: waiting for frames or for the first map)
    MAPPER_BUSY = 17  # mapper: 1 during a mapping step
    TRACKER_BEAT = 18  # tracker: time.monotonic() of its latest sign of life (loop pass or optimiser iteration)
    MAPPER_BEAT = 19  # mapper: the same
    MAP_BYTES = 20  # mapper: bytes of the field's parameters (grows with the explored area)
    KEYFRAME_BYTES = 21  # mapper: bytes of the keyframe store (bounded by mapping.keyframe_budget_mb)
    KEYFRAMES_KEPT = 22  # mapper: keyframes in the store
    TRACKER_DEVICE_PEAK_MB = 23  # tracker: peak GPU memory of its tensors (0 on the CPU)
    MAPPER_DEVICE_PEAK_MB = 24  # mapper: the same
    CONSISTENCY_PAIRS = 25  # mapper: keyframe pairs of the newest consistency score (0: none yet)
    CONSISTENCY_MM = 26  # mapper: SceneMap.consistency() median, mm
    CONSISTENCY_AGREE = 27  # mapper: its share within 3 cm
    # The per-stage profile (seconds, summed; see STAGES): where each worker's time goes.
    TRACK_PREPARE_S = 28  # tracker: the ring's images as the method's tensors (prepare_frame)
    TRACK_ALIGN_S = 29  # tracker: the front end (prediction, relocalization while lost, tracking, quality)
    TRACK_KEYFRAME_S = 30  # tracker: a new keyframe made, handed to the mapper, added to observed space
    TRACK_REPORT_S = 31  # tracker: the pose sent to the parent
    MAP_ADD_S = 32  # mapper: keyframes added to the store (the map's growth test and growth, observed space)
    MAP_STEP_S = 33  # mapper: mapping steps (publications in the middle of a step included)
    MAP_MEASURE_S = 34  # mapper: memory and the consistency score after each step
    TRACK_INDEX_S = 35  # tracker: a loaded map's keyframes indexed for relocalization (while it waits for frames)
    TRACK_WAIT_S = 36  # tracker: waiting for the mapper (the first map; offline, runtime.max_keyframe_lag)
    MAP_CHECK = 37  # mapper: the newest map check (tracking/map_check.py): 0 none yet, 1 agrees, 2 disagrees
    MAP_CHECK_CM = 38  # mapper: its distance between the tracked and the placed keyframe, cm
    MAP_INDEX_S = 39  # mapper: keyframes indexed for relocalization and checked against the map (places.py)
    SUBMAPS = 40  # mapper: submaps in the map (submaps/atlas.py; 1: one map)
    LOOPS_CLOSED = 41  # mapper: loop edges the pose graph kept
    LOOP_CORRECTION_S = 42  # mapper: the newest loop's seconds of input from the revisit to the corrected map
    TRACKED_INDEX = 43  # tracker: the newest tracked frame's index
    TRACKED_STAMP = 44  # tracker: and its stamp
    TRACK_GC_S = 45  # tracker: full garbage collections (cpu.FullCollections)
    MAP_GC_S = 46  # mapper: the same


# The stage counters, each with the events it is divided by: (stage, seconds, events, events not timed). The
# mapper's first step is the warm-up (not in its stage counters): its stages count the steps after it.
STAGES = (
    ("tracker: map read", Counter.READ_SECONDS, Counter.TRACKED, 0),
    ("tracker: frame preparation", Counter.TRACK_PREPARE_S, Counter.TRACKED, 0),
    ("tracker: front end (tracking)", Counter.TRACK_ALIGN_S, Counter.TRACKED, 0),
    ("tracker: new keyframe (hand-over)", Counter.TRACK_KEYFRAME_S, Counter.KEYFRAMES, 1),
    ("tracker: a loaded map's keyframes indexed", Counter.TRACK_INDEX_S, Counter.KEYFRAMES, 1),
    ("tracker: pose to the parent", Counter.TRACK_REPORT_S, Counter.TRACKED, 0),
    ("tracker: waiting for the mapper", Counter.TRACK_WAIT_S, Counter.TRACKED, 0),
    ("mapper: keyframes added (growth, observed space)", Counter.MAP_ADD_S, Counter.MAPPING_STEPS, 1),
    ("mapper: mapping step", Counter.MAP_STEP_S, Counter.MAPPING_STEPS, 1),
    ("mapper: map publication", Counter.PUBLISH_SECONDS, Counter.PUBLISHES, 0),
    ("mapper: memory and consistency", Counter.MAP_MEASURE_S, Counter.MAPPING_STEPS, 0),
    ("mapper: keyframe indexed (relocalization, map check)", Counter.MAP_INDEX_S, Counter.KEYFRAMES, 1),
    ("tracker: full garbage collections", Counter.TRACK_GC_S, Counter.TRACKED, 0),
    ("mapper: full garbage collections", Counter.MAP_GC_S, Counter.MAPPING_STEPS, 1),
)


def stage_profile(counters: dict) -> list[dict]:
    """The per-stage profile from the workers' counters (`HealthBoard.snapshot`): milliseconds per event (tracked
    frame, keyframe, mapping step or publication) and seconds in all."""
    rows = []
    for name, seconds, events, untimed in STAGES:
        s, n = counters.get(seconds.name.lower(), 0.0), counters.get(events.name.lower(), 0.0) - untimed
        rows.append({"stage": name, "per": events.name.lower(), "ms": 1000.0 * s / n if n > 0 else float("nan"),
                     "total_s": s})
    return rows


class HealthBoard:
    """Shared counters; each is written by a single process (see `Counter`), so updates need no lock."""

    def __init__(self):
        self.values = torch.zeros(len(Counter), dtype=torch.float64).share_memory_()

    def get(self, c: Counter) -> float:
        return float(self.values[c])

    def set(self, c: Counter, value: float) -> None:
        self.values[c] = value

    def add(self, c: Counter, value: float = 1.0) -> None:
        self.values[c] += value

    @contextmanager
    def timed(self, c: Counter):
        """`with board.timed(c):` adds the block's seconds to c."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self.add(c, time.perf_counter() - start)

    def unmapped_keyframes(self) -> int:
        """Keyframes the tracker made that are not mapped yet: still in the queue, or received and waiting (or in
        the step under way)."""
        return int(self.get(Counter.KEYFRAMES) - self.get(Counter.KEYFRAMES_RECEIVED)
                   + self.get(Counter.KEYFRAME_BACKLOG))

    def snapshot(self) -> dict:
        return {c.name.lower(): float(v) for c, v in zip(Counter, self.values.tolist())}


class Control:
    """Flags from the parent to the workers, polled by them between (and during) their steps."""

    STOP_NOW, EXIT, EPOCH = 0, 1, 2

    def __init__(self):
        self.flags = torch.zeros(3, dtype=torch.int64).share_memory_()

    def request_stop(self) -> None:
        """Stop working now: no more frames tracked, the current mapping step abandoned."""
        self.flags[self.STOP_NOW] = 1

    def request_exit(self) -> None:
        self.flags[self.EXIT] = 1

    def new_epoch(self) -> int:
        """A reset: workers forget their state; messages of older epochs are ignored."""
        self.flags[self.EPOCH] += 1
        return int(self.flags[self.EPOCH])

    @property
    def stopping(self) -> bool:
        return bool(self.flags[self.STOP_NOW])

    @property
    def exiting(self) -> bool:
        return bool(self.flags[self.EXIT])

    @property
    def epoch(self) -> int:
        return int(self.flags[self.EPOCH])
