"""~/mesh: the map as block markers, re-sent only where it changed, meshed by a low-priority process.

What a subscriber gets
    The map is cut into world blocks (`mesh_block_size`, integer block coordinates; see
    eslam_core/outputs/mesh_blocks.py), one TRIANGLE_LIST marker per block, its id derived from the block's
    coordinates. Each update on ~/mesh carries only what changed since the previous one: an ADD for every block
    whose surface changed (the same id, so RViz and Foxglove replace just that block) and a DELETE for every block
    that became empty. An update is one message, or several of at most about a megabyte when it is larger (see
    "Cost"). A DELETEALL is sent only when the map is reset.
Late subscribers
    A message holds only changes, so the last one alone (what transient local keeps) does not give a newcomer the
    map. A full message (an ADD for every current block; subscribers that have them just redraw them) is published
    - when a subscription matches the publisher: a new RViz display, `ros2 bag record`, a foxglove_bridge that
      subscribes once per client (ros-foxglove-bridge);
    - as every FULL_EVERY-th update: any viewer has the whole map within that many messages, also behind a bridge
      that subscribes once and hands its cached last message to new clients (the foxglove-sdk bridge);
    - once when the mesh rests (nothing sent for `rest_s` after a change): so the last message, the one transient
      local keeps and bridges cache, is complete whenever the map is not changing.
    A full update is always one message, however large. The publisher stays transient local, so that subscribers
    configured that way still match.
Cost
    Meshing runs in a process at nice 19 (`BackgroundMesher`): the node's process only takes the map snapshot and
    writes the message bytes, from the soups the mesh process leaves in shared memory (it keeps every block; a full
    message is a job that asks for all of them). Each job meshes for at most `mesh_time_budget` seconds (dirty
    blocks first), so the first mesh of a large map arrives in pieces, one update each, rather than after one long
    stall. rclpy holds the interpreter lock while it publishes (tens of milliseconds for a message of several
    megabytes on 2 busy cores), which delayed the poses published from the node's other thread: an update that is
    not full is cut into messages of at most MAX_MESSAGE_BYTES, with a short pause between them. Even at SCHED_IDLE
    the mesh process slows the tracker's slowest frames (caches and memory are shared), so it works at most `duty`
    of the time: after a job of t seconds the next starts t * (1 / duty - 1) seconds later. The process is started
    at the first tick, so that its seconds of importing torch are over before the first frames. A new snapshot is
    taken every `mesh_period` seconds when the map changed; until then, jobs continue on the last one while blocks
    are still dirty. The figures of the last job are in ~/status (`mesh_*`).
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Optional

from eslam_core.outputs.mesh import EmptyMeshError
from eslam_core.runtime.mesher import BackgroundMesher, MesherCrashed, MeshSnapshot, MeshUpdate, PackedSnapshot
from eslam_ros.mesh_markers import TriangleBlock, block_message_parts, serialize_block_markers

# Seconds between two looks at the mesh process (its results, new subscribers, the next job).
MESH_POLL_S = 0.2
# Every this many updates one carries every block (see "Late subscribers").
FULL_EVERY = 10
# Messages of an update that is not full (see "Cost"), and the pause between them.
MAX_MESSAGE_BYTES = 1 << 20
PART_PAUSE_S = 0.002
NAMESPACE = "eslam_mesh"


@dataclass
class MeshFigures:
    """What ~/status reports about the mesh (the `mesh_` prefix is added there)."""

    publications: int = 0  # messages on ~/mesh
    full_publications: int = 0  # of them: every block (a new subscriber, every FULL_EVERY-th, at rest)
    blocks: int = 0  # blocks with surface, as published
    triangles: int = 0  # triangles of those blocks, as published (after thinning)
    blocks_sent_last: int = 0  # added or replaced by the last message
    blocks_deleted_last: int = 0
    blocks_meshed_last: int = 0  # by the last job
    blocks_pending: int = 0  # dirty blocks the mesh process has not meshed yet
    job_ms_last: float = 0.0  # wall time of the last job in the mesh process
    job_cpu_ms_last: float = 0.0  # its CPU time
    snapshot_ms_last: float = 0.0  # in the node: the runtime's snapshot and its conversion for the mesh process
    publish_ms_last: float = 0.0  # in the node: writing and publishing the last message
    cpu_s_total: float = 0.0  # CPU seconds the mesh process spent in all
    errors: int = 0  # jobs that failed, and restarts of the mesh process


class MeshPublication:
    """Drives the mesh process and publishes its block updates. `tick` runs on one thread (the node's slow callback
    group); `reset` and `subscriber_matched` may come from any thread."""

    def __init__(self, publish: Callable[[bytes], None], frame_id: str, now: Callable[[], Any], logger: Any, *,
                 resolution: float, block_size: float, period: float, budget_s: float, triangle_budget: int,
                 nice: int = 19, duty: float = 1.0, full_every: int = FULL_EVERY,
                 rest_s: Optional[float] = None) -> None:
        self._publish, self.frame_id, self._now, self.log = publish, frame_id, now, logger
        if not 0 < duty <= 1:
            raise ValueError(f"mesh duty ({duty}) must be in (0, 1]: the share of the time the mesh process works")
        self.period, self.duty = period, duty
        self.full_every = full_every
        self.rest_s = max(2 * period, 2.0) if rest_s is None else rest_s
        self._since_full = 0  # updates since the last full one
        self._last_sent = -float("inf")
        self.mesher = BackgroundMesher(resolution, block_size, budget_s, triangle_budget, nice)
        self.figures = MeshFigures()
        self._published: set[tuple] = set()  # the blocks subscribers have
        self._lock = threading.Lock()
        self._full_wanted = False  # set without the lock: the executor's thread must not wait for a mesh message
        self._meshed_version: Any = None  # map version of the last snapshot
        self._last_snapshot = -float("inf")
        self._rest_until = -float("inf")  # no job starts before (see "Cost")

    # ------------------------------------------------------------------------------------------ events

    def subscriber_matched(self, status: Any) -> None:
        """Publisher matched-event callback: a new subscriber gets every block at the next tick."""
        if getattr(status, "current_count_change", 1) > 0:
            self._full_wanted = True

    def reset(self) -> None:
        """A new map: subscribers drop every block (the one DELETEALL), the mesh process forgets the old map."""
        with self._lock:
            self._forget_map()

    def close(self) -> None:
        with self._lock:
            self.mesher.close()

    # ------------------------------------------------------------------------------------------ the tick

    def tick(self, runtime: Any) -> None:
        """One look at the mesh process, for a SLAM runtime (its map version and `mesh_snapshot()`)."""
        self.step(runtime.health().map_version, runtime.mesh_snapshot)

    def step(self, map_version: Any, take_snapshot: Callable[[set], MeshSnapshot | PackedSnapshot]) -> None:
        """Publish the mesh process's update if one is ready, every block if a subscriber is new, and start the
        next job when one is due: a new snapshot (`take_snapshot(ids of the keyframes whose depth the process
        has)`) every `period` seconds if the map version changed, else a continuation while blocks are dirty; none
        while the process rests (see "Cost")."""
        if not self.mesher.running:
            # Outside the lock (seconds: a new interpreter imports torch), so that reset() never waits for it.
            try:
                self.mesher.start()
            except MesherCrashed as error:
                self.figures.errors += 1
                self.log.error(f"{error}; trying again at the next tick", throttle_duration_sec=30.0)
                return
        with self._lock:
            try:
                update = self.mesher.poll()
            except MesherCrashed as error:
                self._restart(f"{error}; restarting it and clearing the published mesh")
                return
            if update is not None:
                self._apply(update)
                self._rest_until = time.monotonic() + update.wall_s * (1.0 / self.duty - 1.0)
            if self.mesher.busy or time.monotonic() < self._rest_until:
                return
            epoch, have = self.mesher.epoch, self.mesher.have()
            # Version 0: nothing fitted yet (a still random map would only cost time to mesh).
            due = (bool(map_version) and map_version != self._meshed_version
                   and time.monotonic() - self._last_snapshot >= self.period)
            if not due:
                if self.mesher.pending or self._full_due():
                    self._submit(None)
                return
        start = time.monotonic()
        try:
            # Outside the lock: the snapshot waits for the runtime (the mapper's answer, or the step in progress).
            snapshot = take_snapshot(have)
        except EmptyMeshError:
            return  # nothing mapped yet
        with self._lock:
            if self.mesher.epoch != epoch or self.mesher.busy or self.mesher.have() != have:
                return  # reset or restarted meanwhile: this snapshot may be of the old map, or lack depth images
            self._meshed_version, self._last_snapshot = map_version, time.monotonic()
            self.figures.snapshot_ms_last = 1000 * (time.monotonic() - start)
            self._submit(snapshot)

    def _full_due(self) -> bool:
        """Every block is wanted now: by a new subscriber, or because the mesh rests (see "Late subscribers")."""
        if not self._published:
            self._full_wanted = False  # nothing to send yet; the first blocks reach every subscriber anyway
            return False
        resting = (self._since_full and not self.mesher.pending
                   and time.monotonic() - self._last_sent >= self.rest_s)
        return self._full_wanted or bool(resting)

    def _submit(self, snapshot: MeshSnapshot | PackedSnapshot | None) -> None:
        """Start a job; it brings every block back (a full message) when one is due or the FULL_EVERY-th is next."""
        everything = self._full_due() or (bool(self._published) and self._since_full + 1 >= self.full_every)
        if everything:
            self._full_wanted = False
        try:
            self.mesher.submit(snapshot, everything=everything)
        except MesherCrashed as error:
            self._restart(f"{error}; restarting it and clearing the published mesh")

    # ------------------------------------------------------------------------------------------ messages

    def _apply(self, update: MeshUpdate) -> None:
        f = self.figures
        if update.error:
            f.errors += 1
            self.log.warning(f"meshing failed (the mesh starts over with the next snapshot): {update.error}",
                             throttle_duration_sec=30.0)
            self._meshed_version = None
            return
        if update.epoch != self.mesher.epoch:
            return  # a job from before the last reset
        f.blocks_meshed_last, f.blocks_pending = update.meshed, update.pending
        f.job_ms_last, f.job_cpu_ms_last = 1000 * update.wall_s, 1000 * update.cpu_s
        f.cpu_s_total += update.cpu_s
        changed = {key: TriangleBlock(corners, colors) for key, (corners, colors) in update.changed.items()}
        removed = [key for key in update.removed if key in self._published]
        self._published.difference_update(removed)
        self._published.update(changed)
        f.blocks, f.triangles = update.blocks, update.triangles
        if update.everything or changed or removed:
            self._send(changed, removed, update.everything)

    def _send(self, blocks: dict, removed: list, full: bool) -> None:
        """Publish an update: a full one as one message (see "Late subscribers"), the others in parts of at most
        MAX_MESSAGE_BYTES, with a pause between them for the node's other threads (see "Cost")."""
        start = time.monotonic()
        parts = [blocks] if full else block_message_parts(blocks, MAX_MESSAGE_BYTES)
        stamp = self._now()  # one update, one stamp
        for number, part in enumerate(parts):
            if number:
                time.sleep(PART_PAUSE_S)
            self._publish(serialize_block_markers(part, [] if number else removed, self.frame_id, stamp, NAMESPACE))
        f = self.figures
        f.publications += len(parts)
        f.full_publications += int(full)
        f.blocks_sent_last, f.blocks_deleted_last = len(blocks), len(removed)
        f.publish_ms_last = 1000 * (time.monotonic() - start)
        self._since_full = 0 if full else self._since_full + 1
        self._last_sent = time.monotonic()

    def _restart(self, message: str) -> None:
        """The mesh process died: a fresh one rebuilds every block, so subscribers drop theirs first."""
        self.figures.errors += 1
        self.log.error(message, throttle_duration_sec=30.0)
        self._forget_map()

    def _forget_map(self) -> None:
        """Subscribers drop every block (the one DELETEALL), the mesh process forgets the old map."""
        self.mesher.reset()
        # (A DELETEALL of a namespace leaves other namespaces' markers: submaps' blocks are deleted one by one.)
        submaps = [key for key in self._published if len(key) == 4]
        self._published.clear()
        self._meshed_version, self._last_snapshot = None, -float("inf")
        self.figures.blocks = self.figures.triangles = self.figures.blocks_pending = 0
        self._publish(serialize_block_markers({}, submaps, self.frame_id, self._now(), NAMESPACE, delete_all=True))
        self.figures.publications += 1
        self._since_full = 0  # an empty map, completely described

    def status(self) -> dict[str, Any]:
        """The figures for ~/status, named `mesh_<figure>` (and the older `meshes_published`, `mesh_triangles`)."""
        with self._lock:
            values = {f"mesh_{name}": value for name, value in vars(self.figures).items()}
            values["mesh_busy"] = self.mesher.busy  # a job is running in the mesh process
        values["meshes_published"] = values.pop("mesh_publications")
        return values
