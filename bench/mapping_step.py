"""Cost of one mapping step (`Mapper.map`, the whole step as the mapper runs it) on a map of growing size.

    python bench/mapping_step.py --data ../shared/data/icl_office_kt0 [--config fast] [--grow 0,3,6] [--threads 1]

A map is warmed up on frame 0, then the step maps a window of five keyframes spread over the first 60 frames (their
ground-truth poses) again and again; with `--grow G` the map's extent is first grown by G metres on every side: the
same rays, more plane rows (what a camera that goes anywhere does to the map). Prints the median step time per size.
Uses only what every version of the mapper has, so that it can time an older checkout too (copy it there).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from eslam_core.cli import open_configured_dataset  # noqa: E402
from eslam_core.config import load_config  # noqa: E402
from eslam_core.frames import pixel_directions_table, prepare_frame, working_intrinsics  # noqa: E402
from eslam_core.mapping.keyframes import Keyframe  # noqa: E402
from eslam_core.mapping.mapper import Mapper  # noqa: E402
from eslam_core.slam import SLAM  # noqa: E402


def step_times(cfg, ds, grow: float, steps: int) -> tuple[int, list[float]]:
    torch.manual_seed(0)
    slam = SLAM(cfg, ds.intrinsics)
    cfg.mapping.first_iterations = 30
    slam.step(ds[0])
    if grow > 0:
        slam.map.grow(slam.map.extent + np.array([[-grow] * 3, [grow] * 3]))
    field = slam.map.field
    intr = working_intrinsics(ds.intrinsics, cfg.camera)
    keyframes = []
    for i in np.linspace(1, min(61, len(ds) - 1), 5).astype(int):
        frame = ds[int(i)]
        if frame.pose is None:
            raise SystemExit(f"frame {i} has no ground-truth pose: this benchmark needs a data set with poses")
        f = prepare_frame(frame, ds.intrinsics, cfg.camera)
        keyframes.append(Keyframe.from_tensors(int(i), 0.0, f.rgb, f.depth, f.depth >= 0,
                                               torch.from_numpy(frame.pose).float()))
    mapper = Mapper.of(cfg, pixel_directions_table(intr), intr.height, intr.width)
    window = list(range(len(keyframes)))
    times = []
    for _ in range(steps + 2):  # the first two warm up
        start = time.perf_counter()
        mapper.map(field, keyframes, window)
        times.append(time.perf_counter() - start)
    return field.geometry_planes.layout.rows + field.appearance_planes.layout.rows, times[2:]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True, help="data set folder with ground-truth poses")
    ap.add_argument("--kind", default=None, help="data set kind (default: icl for icl_* folders, else auto)")
    ap.add_argument("--config", default="fast", help="preset or YAML (default fast)")
    ap.add_argument("--grow", default="0,6", help="comma-separated metres to grow the map by on every side")
    ap.add_argument("--steps", type=int, default=10, help="timed steps per size")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1: a worker's share)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    kind = args.kind or ("icl" if "icl" in args.data.name else "auto")
    print(f"{'grown by':>9s} {'plane rows':>11s} {'planes MB':>10s} {'step ms (median)':>17s} {'min':>7s} {'max':>7s}")
    for grow in (float(g) for g in args.grow.split(",")):
        cfg = load_config(args.config, {"dataset": {"kind": kind}})
        ds = open_configured_dataset(cfg, args.data, (0, 62), 1)
        rows, times = step_times(cfg, ds, grow, args.steps)
        ms = [1000 * t for t in times]
        print(f"{grow:8.1f}m {rows:11d} {rows * cfg.model.channels * 4 / 2**20:10.1f} {statistics.median(ms):17.1f} "
              f"{min(ms):7.1f} {max(ms):7.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
