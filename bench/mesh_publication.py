"""Cost of publishing the live mesh: the whole map at every publication (before) against block updates meshed by
the nice-19 mesh process (now), on a map built from the synthetic room.

    python bench/mesh_publication.py [--frames 60] [--more 12] [--resolution 0.04] [--block-size 1.0] [--budget 0.5]

1. Builds a map: the `fast` preset, lock-step, on the first --frames frames of the synthetic room (320x240).
2. Before: `map_mesh` of the whole map (what the node published until now, via save_mesh and a PLY file) and the
   CDR bytes of its MarkerArray: all in the node's process.
3. Now, first mesh: the map's snapshot for the mesh process (node side), then jobs of at most --budget seconds in the
   mesh process until no block is dirty; each job's blocks as one message (node side: writing the bytes).
4. Now, an update: --more frames later (new keyframes, mapping steps), a new snapshot and the jobs it takes: how
   many blocks were re-meshed, how many re-sent, and the message size against a full mesh.
Wall and CPU milliseconds; the mesh process runs at nice 19, so its wall time depends on the machine's load (the
load average is printed).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from eslam_core.config import load_config  # noqa: E402
from eslam_core.datasets import open_dataset  # noqa: E402
from eslam_core.datasets.synthetic import ensure_scene  # noqa: E402
from eslam_core.demo import default_cache  # noqa: E402
from eslam_core.outputs.export import map_mesh  # noqa: E402
from eslam_core.runtime.mesher import BackgroundMesher, snapshot_for_meshing  # noqa: E402
from eslam_core.slam import SLAM  # noqa: E402
from eslam_ros.mesh_markers import TriangleBlock, serialize_block_markers, serialize_mesh_marker_array  # noqa: E402


def timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, 1000 * (time.perf_counter() - wall), 1000 * (time.process_time() - cpu)


def run_jobs(mesher: BackgroundMesher, snapshot, label: str) -> dict:
    """Jobs until nothing is dirty; prints one row per job (= one message)."""
    blocks, job = {}, 0
    totals = dict(jobs=0, wall=0.0, cpu=0.0, sent=0, meshed=0, bytes=0, write_ms=0.0)
    mesher.submit(snapshot)
    while True:
        while (update := mesher.poll()) is None:
            time.sleep(0.005)
        assert not update.error, update.error
        changed = {k: TriangleBlock(c, col) for k, (c, col) in update.changed.items()}
        data, write_ms, _ = timed(lambda: serialize_block_markers(changed, update.removed, "map", 0.0, "eslam_mesh"))
        blocks.update(changed)
        print(f"  {label} job {job}: {update.wall_s * 1000:7.0f} ms wall, {update.cpu_s * 1000:6.0f} ms CPU, "
              f"{update.meshed:3d} blocks meshed, {len(update.changed):3d} sent, {len(update.removed)} deleted, "
              f"{update.pending:3d} pending; message {len(data) / 1e6:5.2f} MB written in {write_ms:4.1f} ms")
        totals["jobs"] += 1
        totals["wall"] += update.wall_s * 1000
        totals["cpu"] += update.cpu_s * 1000
        totals["sent"] += len(update.changed)
        totals["meshed"] += update.meshed
        totals["bytes"] += len(data)
        totals["write_ms"] += write_ms
        totals["blocks"], totals["triangles"] = update.blocks, update.triangles
        job += 1
        if not update.pending:
            return totals
        mesher.submit(None)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--more", type=int, default=12, help="frames between the first mesh and the update")
    ap.add_argument("--resolution", type=float, default=0.04, help="mesh voxel (m); the node's shipped value")
    ap.add_argument("--block-size", type=float, default=1.0)
    ap.add_argument("--budget", type=float, default=0.5, help="seconds per job")
    ap.add_argument("--triangle-budget", type=int, default=100_000)
    args = ap.parse_args()

    torch.set_num_threads(1)
    data = open_dataset(ensure_scene(default_cache(), n_frames=args.frames + args.more, width=320, height=240,
                                     seed=0), "tum")
    slam = SLAM(load_config("fast"), data.intrinsics)
    _, build_ms, _ = timed(lambda: [slam.step(data[i]) for i in range(args.frames)])
    print(f"map: {args.frames} frames of the synthetic room (320x240), {len(slam.map.keyframes)} keyframes, "
          f"{build_ms / 1000:.1f} s; load average {os.getloadavg()[0]:.1f}")

    mesh, mesh_ms, mesh_cpu = timed(lambda: map_mesh(slam, args.resolution))
    _, bytes_ms, _ = timed(lambda: serialize_mesh_marker_array(
        mesh.vertices, mesh.faces, mesh.visual.vertex_colors[:, :3], "map", 0.0, triangle_budget=args.triangle_budget))
    print(f"before (whole map in the node's process, {args.resolution} m): {mesh_ms:.0f} ms wall, {mesh_cpu:.0f} ms "
          f"CPU for {len(mesh.faces)} triangles, + {bytes_ms:.0f} ms for the message, at every publication")

    mesher = BackgroundMesher(args.resolution, args.block_size, args.budget, args.triangle_budget, nice=19)
    _, start_ms, _ = timed(mesher.start)
    print(f"now ({args.block_size} m blocks, {args.budget} s per job, nice 19); mesh process started in "
          f"{start_ms:.0f} ms")
    snapshot, snap_ms, snap_cpu = timed(lambda: snapshot_for_meshing(slam.atlas, mesher.have()))
    print(f"  first snapshot for the mesh process: {snap_ms:.0f} ms in the node ({len(snapshot.field) / 1e6:.1f} MB "
          f"field, {len(snapshot.new_depths)} depth images)")
    first = run_jobs(mesher, snapshot, "first")
    print(f"  first mesh: {first['jobs']} messages, {first['blocks']} blocks, {first['triangles']} triangles; mesh "
          f"process {first['wall']:.0f} ms wall / {first['cpu']:.0f} ms CPU in all; node {snap_ms:.0f} ms snapshot + "
          f"{first['write_ms']:.1f} ms writing {first['bytes'] / 1e6:.2f} MB")

    for i in range(args.frames, args.frames + args.more):
        slam.step(data[i])
    snapshot, snap_ms, _ = timed(lambda: snapshot_for_meshing(slam.atlas, mesher.have()))
    update = run_jobs(mesher, snapshot, "update")
    print(f"  update after {args.more} more frames ({len(slam.map.keyframes)} keyframes): node {snap_ms:.0f} ms "
          f"snapshot ({len(snapshot.new_depths)} new depth images) + {update['write_ms']:.1f} ms writing "
          f"{update['bytes'] / 1e6:.2f} MB ({100 * update['bytes'] / max(first['bytes'], 1):.0f} % of the first mesh); "
          f"mesh process {update['wall']:.0f} ms wall / {update['cpu']:.0f} ms CPU, {update['meshed']} blocks "
          f"re-meshed, {update['sent']} of {update['blocks']} re-sent")
    mesher.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
