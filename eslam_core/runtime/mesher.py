"""Meshing the live map in a process of its own, at the lowest CPU priority: the mesh preview must not take time
from tracking and mapping.

Why a process: a thread would share the caller's interpreter lock, and a low-priority thread that holds it while
the CPU is busy stalls the caller's other threads (the node's pose publication) until it is scheduled again; the
scheduler also cannot tell such a thread from the caller. A process at nice 19 (and Linux's SCHED_IDLE, see
cpu.lower_priority) gets only the CPU time that tracking and mapping leave, and nothing of the caller's.

Protocol (one job at a time; the caller waits for a job's `MeshUpdate` before it submits the next):
    caller                                   mesh process
    submit(snapshot)      ---- map ---->     IncrementalMesher.update(view, budget) ----+
    submit(None)          ---- continue -->  (same map: the blocks still dirty)          |
    submit(.., everything=True)  -------->   (the same, and every block comes back, not only the changed ones)
    poll() -> MeshUpdate  <--- blocks -------------------------------------------------+
    reset()               ---- reset --->    forget everything (a new map)
A snapshot carries the field and every keyframe pose, but only the depth images the process does not have yet; it
travels as a PackedSnapshot, pickled into shared memory by whoever took it (in the runtime: the mapping process).
Blocks come back as triangle soups (corners float64, RGBA float32), thinned to the triangle budget, in one
shared-memory buffer (PackedSoups): the caller writes them into a message from there, without another copy. The
process keeps every block, so the caller keeps none: it asks for all of them when it needs them all.
"""
from __future__ import annotations

import io
import logging
import multiprocessing
import os
import pickle
import time
import traceback
from dataclasses import dataclass, field
from typing import Any, Hashable, Optional

import numpy as np
import torch
import torch.multiprocessing  # noqa: F401 - registers the reductions that send a shared tensor as a handle

from eslam_core.camera import Intrinsics
from eslam_core.child_process import become_child, spawned_with_stop_signals_blocked, wait_for_start
from eslam_core.cpu import freeze_start_up_objects, lower_priority
from eslam_core.outputs.mesh import MeshSettings
from eslam_core.outputs.mesh_blocks import (BlockLayout, IncrementalMesher, Key, MeshSource, mesh_source, thinning_stride,
                                            triangle_soup)

log = logging.getLogger("eslam")

# Most triangles in one block's soup: RViz and Foxglove draw a marker as one vertex buffer; a block over it is
# thinned like the whole mesh is over its budget.
MAX_BLOCK_TRIANGLES = 65536
# Starting: no CPU progress for this long is a hung child (child_process.wait_for_start); nor may it take longer.
START_STALLED_S = 60.0
START_LIMIT_S = 900.0


class MesherCrashed(RuntimeError):
    """The mesh process died; the message has its exit code or traceback."""


@dataclass
class MeshSnapshot:
    """The map as the mesh process needs it (see `snapshot_for_meshing`)."""

    field: bytes  # the field module, torch.save'd: decoders and feature planes
    bound: np.ndarray  # (2, 3)
    truncation: float
    intrinsics: Intrinsics
    keyframe_ids: list[Hashable]
    poses: np.ndarray  # (K, 4, 4)
    new_depths: dict  # keyframe id -> (H, W) float32 depth image, for the keyframes the process has not got yet
    # With submaps (submaps/atlas.py): the submap all the above is of (in its frame), and every submap's anchor (its
    # frame's world pose). Empty: one map in the world frame, its blocks keyed (i, j, k); else (submap, i, j, k).
    submap: int = 0
    anchors: dict = field(default_factory=dict)


@dataclass
class PackedSoups:
    """Triangle soups of map blocks in one shared-memory buffer: the corners (float64) of every block, then their
    colours (float32). Pickled through the pipe instead, the 10 MB of an 80 k-triangle update held the ROS node's
    interpreter lock for 5-7 ms to unpickle, and its poses waited."""

    keys: list
    triangles: list  # per block
    data: Optional[torch.Tensor] = None  # uint8, in shared memory; None without triangles

    @staticmethod
    def of(soups: dict[Key, tuple[np.ndarray, np.ndarray]]) -> "PackedSoups":
        keys = list(soups)
        triangles = [len(soups[key][0]) // 3 for key in keys]
        if not sum(triangles):
            return PackedSoups(keys, triangles)
        per_triangle = 3 * (3 * 8 + 4 * 4)  # three corners, each xyz float64 and RGBA float32
        packed = PackedSoups(keys, triangles,
                             torch.empty(sum(triangles) * per_triangle, dtype=torch.uint8).share_memory_())
        for (corners, colors), (out_corners, out_colors) in zip(soups.values(), packed.unpack().values()):
            out_corners[:], out_colors[:] = corners, colors
        return packed

    def unpack(self) -> dict[Key, tuple[np.ndarray, np.ndarray]]:
        """Block -> (corners (3T, 3) float64, colours (3T, 4) float32), views of the buffer."""
        total = 3 * sum(self.triangles)
        raw = self.data.numpy() if self.data is not None else np.zeros(0, np.uint8)
        corners, colors = raw[:24 * total].view("<f8").reshape(-1, 3), raw[24 * total:].view("<f4").reshape(-1, 4)
        ends = np.cumsum([0] + [3 * t for t in self.triangles])
        return {key: (corners[a:b], colors[a:b]) for key, a, b in zip(self.keys, ends[:-1], ends[1:])}


@dataclass
class MeshUpdate:
    """What a job changed: blocks to (re)draw and blocks to delete, and what it cost."""

    epoch: int
    soups: PackedSoups = field(default_factory=lambda: PackedSoups([], []))  # the blocks to (re)draw
    removed: list[Key] = field(default_factory=list)
    everything: bool = False  # `soups` has every block of the map (asked for), not only the changed ones
    blocks: int = 0  # non-empty blocks after the update
    triangles: int = 0  # triangles sent for them in all (after thinning)
    stride: int = 1  # every stride-th triangle is sent
    meshed: int = 0  # blocks meshed by the job
    pending: int = 0  # dirty blocks left for the next job
    wall_s: float = 0.0
    cpu_s: float = 0.0
    error: str = ""  # the traceback of a job that failed (the process goes on)

    @property
    def changed(self) -> dict[Key, tuple[np.ndarray, np.ndarray]]:
        """Blocks to (re)draw: soups (corners, colours)."""
        return self.soups.unpack()


@dataclass
class PackedSnapshot:
    """A MeshSnapshot pickled where it is made (in the runtime: the mapping process) into shared memory: it goes to
    the mesh process through the caller as a handle, not as bytes. Unpickled and pickled again in the ROS node, the
    10-30 MB of a snapshot held the node's interpreter lock for tens of milliseconds, and its poses waited."""

    keyframe_ids: list
    data: torch.Tensor  # uint8, in shared memory (torch.multiprocessing passes its file descriptor)

    @staticmethod
    def of(snapshot: MeshSnapshot) -> "PackedSnapshot":
        raw = pickle.dumps(snapshot, pickle.HIGHEST_PROTOCOL)
        data = torch.empty(len(raw), dtype=torch.uint8).share_memory_()
        data.numpy()[:] = np.frombuffer(raw, dtype=np.uint8)
        return PackedSnapshot(list(snapshot.keyframe_ids), data)

    def unpack(self) -> MeshSnapshot:
        return pickle.loads(memoryview(self.data.numpy()))


def snapshot_for_meshing(atlas, have: set) -> MeshSnapshot:
    """The map of an Atlas (`SLAM.atlas`; in the runtime the mapping process's, see `mesh_snapshot`) as a
    MeshSnapshot: its active submap, and with submaps every submap's anchor; `have`: keyframe ids whose depth was
    sent."""
    scene = atlas.active
    view = mesh_source(scene, skip_depths=have)
    buffer = io.BytesIO()
    torch.save(scene.field, buffer)
    anchors = {sub.number: atlas.anchor(sub) for sub in atlas.submaps} if atlas.cfg.submaps.radius_m > 0 else {}
    return MeshSnapshot(buffer.getvalue(), view.bound, view.truncation, view.intrinsics, list(view.keyframe_ids),
                        view.poses, {k: d for k, d in zip(view.keyframe_ids, view.depths) if d is not None},
                        scene.number, anchors)


@dataclass(frozen=True)
class _Setup:
    resolution: float
    block_size: float
    budget_s: float
    triangle_budget: int
    nice: int
    parent_pid: int


@dataclass(frozen=True)
class _Job:
    epoch: int
    snapshot: Optional[PackedSnapshot]  # None: continue on the last map
    everything: bool  # send every block, not only the changed ones


@dataclass(frozen=True)
class _Reset:
    epoch: int


# ------------------------------------------------------------------------------------------------ the process


@dataclass
class _Part:
    """One submap's meshing (the map's, without submaps): its blocks, the newest view of it, its anchor."""

    mesher: IncrementalMesher
    view: MeshSource
    anchor: Optional[np.ndarray] = None  # None: the world's frame


class _Worker:
    def __init__(self, setup: _Setup) -> None:
        self.setup = setup
        self.layout = BlockLayout.of(setup.block_size, setup.resolution)
        self.reset()

    def reset(self) -> None:
        self.parts: dict[int, _Part] = {}  # by submap number
        self.submapped = False  # blocks are keyed (submap, i, j, k)
        self.depths: dict = {}
        self.stride = 1

    def run(self, epoch: int, snapshot: Optional[MeshSnapshot], everything: bool = False) -> MeshUpdate:
        wall, cpu = time.monotonic(), time.process_time()
        moved: set[int] = set()
        current = None
        if snapshot is not None:
            current = self._take(snapshot, moved)
        if not self.parts:
            return MeshUpdate(epoch)
        # The submap the snapshot is of first (the one being mapped), then the others' blocks still to mesh.
        order = sorted(self.parts, key=lambda n: (n != current, n))
        changed, removed, meshed, pending = {}, [], 0, 0
        for number in order:
            part = self.parts[number]
            budget = self.setup.budget_s - (time.monotonic() - wall)
            if number != order[0] and (budget <= 0 or not part.mesher.pending):
                pending += part.mesher.pending
                continue
            changes = part.mesher.update(part.view, max(budget, 0.0))
            changed.update({self._key(number, key): mesh for key, mesh in changes.changed.items()})
            removed += [self._key(number, key) for key in changes.removed]
            meshed, pending = meshed + changes.meshed, pending + changes.pending
        blocks = {self._key(number, key): (part, mesh) for number, part in self.parts.items()
                  for key, mesh in part.mesher.blocks.items()}
        stride = thinning_stride(sum(mesh.triangles for _, mesh in blocks.values()), self.setup.triangle_budget)
        # A new stride thins every block anew; a submap that moved (a loop closed) is sent whole where it is now.
        if everything or stride != self.stride:
            resend = set(blocks)
        else:
            resend = set(changed) | {key for key in blocks if self.submapped and key[0] in moved}
        self.stride = stride

        def block_stride(mesh) -> int:  # the map's stride, or more for a block too big for one marker
            return max(stride, thinning_stride(mesh.triangles, MAX_BLOCK_TRIANGLES))

        soups = {key: in_world(triangle_soup(blocks[key][1], block_stride(blocks[key][1])), blocks[key][0].anchor)
                 for key in resend}
        triangles = sum(-(-mesh.triangles // block_stride(mesh)) for _, mesh in blocks.values())
        return MeshUpdate(epoch, PackedSoups.of(soups), removed, everything, len(blocks), triangles, stride,
                          meshed, pending, time.monotonic() - wall, time.process_time() - cpu)

    def _key(self, submap: int, key: Key) -> Hashable:
        return (submap, *key) if self.submapped else key

    def _take(self, snapshot: MeshSnapshot, moved: set) -> int:
        """A snapshot's view of its submap; the submaps whose anchors moved into `moved`. Returns its submap."""
        self.submapped = bool(snapshot.anchors)
        view = self._view(snapshot)
        part = self.parts.get(snapshot.submap)
        if part is None:
            settings = MeshSettings(resolution=self.layout.resolution, truncation=view.truncation)
            part = self.parts[snapshot.submap] = _Part(IncrementalMesher(self.layout, settings), view)
        part.view = view
        for number, anchor in snapshot.anchors.items():
            other = self.parts.get(number)
            if other is not None:
                if other.anchor is not None and not np.array_equal(other.anchor, anchor):
                    moved.add(number)
                other.anchor = np.asarray(anchor)
        # Dropped keyframes are forgotten: those no part's view holds.
        held = {k for p in self.parts.values() for k in p.view.keyframe_ids}
        self.depths = {k: d for k, d in self.depths.items() if k in held}
        return snapshot.submap

    def _view(self, snapshot: MeshSnapshot) -> MeshSource:
        # Bytes the caller's torch.save wrote, through a private pipe (not a file): the module is unpickled whole.
        field_ = torch.load(io.BytesIO(snapshot.field), weights_only=False).eval()
        self.depths.update(snapshot.new_depths)
        missing = [k for k in snapshot.keyframe_ids if k not in self.depths]
        if missing:
            raise ValueError(f"the snapshot lacks the depth images of keyframes {missing[:5]}: build it with the "
                             f"mesher's have() after its last update")
        return MeshSource(field_.sdf, field_.color, snapshot.bound, snapshot.truncation, snapshot.intrinsics,
                          list(snapshot.keyframe_ids), snapshot.poses, [self.depths[k] for k in snapshot.keyframe_ids])


def in_world(soup: tuple[np.ndarray, np.ndarray], anchor: Optional[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """A block's triangle soup (corners in its submap's frame) in the world frame."""
    corners, colors = soup
    if anchor is None:
        return soup
    return np.ascontiguousarray(corners @ anchor[:3, :3].T + anchor[:3, 3], dtype="<f8"), colors


def _serve(connection, setup: _Setup) -> None:
    """The mesh process: jobs in, MeshUpdates out, until told to stop or the caller is gone."""
    become_child("mesh", setup.parent_pid)
    lower_priority(setup.nice)
    torch.set_num_threads(1)
    worker = _Worker(setup)
    freeze_start_up_objects()
    connection.send("ready")
    while True:
        try:
            message = connection.recv()
        except EOFError:  # the caller closed its end
            return
        if message is None:
            return
        if isinstance(message, _Reset):
            worker.reset()
            continue
        try:
            update = worker.run(message.epoch, message.snapshot and message.snapshot.unpack(), message.everything)
        except Exception:  # noqa: BLE001 - reported to the caller; the next job starts from a fresh mesher
            update = MeshUpdate(message.epoch, error=traceback.format_exc())
            worker.reset()
        connection.send(update)


# ------------------------------------------------------------------------------------------------ the caller's side


class BackgroundMesher:
    """The caller's handle on the mesh process (started at the first `submit`). Not thread-safe: one caller thread,
    or a lock around it."""

    def __init__(self, resolution: float, block_size: float = 1.0, budget_s: float = 0.5,
                 triangle_budget: int = 100_000, nice: int = 19) -> None:
        BlockLayout.of(block_size, resolution)  # a clear error now rather than in the process
        if not (budget_s > 0 and triangle_budget >= 1 and 0 <= nice <= 19):
            raise ValueError(f"mesh time budget ({budget_s} s) must be > 0, triangle budget ({triangle_budget}) >= 1 "
                             f"and nice ({nice}) in 0..19")
        self.setup = _Setup(float(resolution), float(block_size), float(budget_s), int(triangle_budget), int(nice),
                            os.getpid())
        self.epoch = 0
        self.busy = False
        self.pending = 0  # dirty blocks the process reported left
        self._have: set = set()  # keyframe ids whose depth images the process has
        self._process: Any = None
        self._connection: Any = None

    @property
    def running(self) -> bool:
        return self._process is not None and self._process.is_alive()

    def start(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._connection, child = ctx.Pipe()
        self._process = ctx.Process(target=_serve, args=(child, self.setup), name="eslam-mesher", daemon=True)
        with spawned_with_stop_signals_blocked():
            self._process.start()
        lower_priority(self.setup.nice, self._process.pid)  # now, before it spends seconds importing torch
        child.close()
        try:
            started = wait_for_start(self._connection, self._process, START_STALLED_S, START_LIMIT_S) and \
                self._receive() == "ready"
        except (EOFError, OSError):
            started = False
        if not started:
            code = self._process.exitcode
            self.close()
            why = f"exit code {code}; see its output above" if code is not None else \
                f"no progress for {START_STALLED_S:.0f} s, or not ready within {START_LIMIT_S:.0f} s"
            raise MesherCrashed(f"the mesh process did not start ({why})")
        self.busy, self.pending, self._have = False, 0, set()

    def submit(self, snapshot: MeshSnapshot | PackedSnapshot | None, everything: bool = False) -> None:
        """Start a job: mesh this map (its depth images for the keyframes the process has not got yet), or continue
        with the blocks still dirty on the last one (None); `everything`: its update has every block, not only the
        changed ones."""
        if self.busy:
            raise RuntimeError("the mesh process is busy: poll() for its update before submitting another job")
        if not self.running:
            self.start()
        if isinstance(snapshot, MeshSnapshot):
            snapshot = PackedSnapshot.of(snapshot)
        if snapshot is not None:
            self._have = set(snapshot.keyframe_ids)
        self._send(_Job(self.epoch, snapshot, everything))
        self.busy = True

    def have(self) -> set:
        """Keyframe ids whose depth images the process has (leave them out of the next snapshot)."""
        return set(self._have)

    def poll(self) -> Optional[MeshUpdate]:
        """The update of the job in progress once it is done (None before); an update of a job from before the
        last reset comes back with its old epoch: drop it. Raises MesherCrashed if the process died."""
        if self._process is None or not self.busy:
            return None
        try:
            if not self._connection.poll(0):
                if not self._process.is_alive():
                    raise EOFError
                return None
            update = self._receive()
        except (EOFError, OSError):
            code = self._process.exitcode
            self._forget_process()
            raise MesherCrashed(f"the mesh process died (exit code {code})") from None
        self.busy = False
        if update.error:
            self._have = set()  # the process starts afresh: the next snapshot carries every depth image
        if update.epoch == self.epoch:
            self.pending = update.pending
        return update

    def reset(self) -> None:
        """A new map: the process forgets blocks and keyframes once its current job is done."""
        self.epoch += 1
        self.pending = 0
        self._have = set()
        if self.running:
            self._send(_Reset(self.epoch))

    def close(self, timeout: float = 5.0) -> None:
        if self._process is None:
            return
        try:
            self._connection.send(None)
        except (OSError, ValueError):
            pass
        self._process.join(timeout)
        if self._process.is_alive():
            self._process.kill()
            self._process.join(timeout)
        self._forget_process()

    def _forget_process(self) -> None:
        if self._connection is not None:
            self._connection.close()
        self._process, self._connection = None, None
        self.busy, self.pending, self._have = False, 0, set()

    def _send(self, message: Any) -> None:
        try:
            self._connection.send(message)
        except (OSError, ValueError):
            code = self._process.exitcode if self._process is not None else None
            self._forget_process()
            raise MesherCrashed(f"the mesh process died (exit code {code})") from None

    def _receive(self) -> Any:
        return self._connection.recv()
