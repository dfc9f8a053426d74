"""Relocalization benchmark: place recognition + PnP RANSAC against keyframes with reference poses.

    python bench/relocalize.py --data ../shared/data/icl_office_kt0 --kind icl
    python bench/relocalize.py --data ../shared/data/7scenes_redkitchen_0_399

The database holds every `--keyframe-every`th frame of the first half of the sequence, at its reference pose; the
queries are every `--query-every`th frame of the second half. A query *sees the map* when at least
`--min-overlap` of its depth points (at its reference pose) are seen by some keyframe at the depth that keyframe
measured (a view of the same things from the other side of the room counts: it is in the map, although no feature
matcher finds it). Reported: recall (queries relocalized within 5 cm / 5 degrees, and within 10 cm / 10 degrees,
over those that see the map), wrong poses (returned but off by more than 10 cm or 10 degrees: the dangerous kind),
pose error of the relocalized ones, time per query (ORB extraction included; wall clock and CPU, OpenCV on one
thread: on a shared machine the CPU time is the steadier figure), and a query on a frame with a covered lens
(black, no depth).

7-Scenes colour is not registered to depth, and its colour camera has a wider view than the depth camera's
nominal intrinsics say (focal length about 525 pixels against 585, as DSAC and later work use): with
`--colour-focal 525` the colour image is resampled onto the depth camera's grid (a zoom about the image centre)
before both the database and the queries see it.

This is the database/query part of the issue's benchmark; the full one maps the first half with ESLAM instead of
using reference poses for the keyframes.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from eslam_core.camera import Intrinsics, backproject  # noqa: E402
from eslam_core.datasets import open_dataset  # noqa: E402
from eslam_core.geometry import rotation_angle_deg  # noqa: E402
from eslam_core.tracking.relocalization import KeyframeDatabase, RelocalizationConfig  # noqa: E402

CORRECT_M, CORRECT_DEG = 0.05, 5.0
COARSE_M, COARSE_DEG = 0.10, 10.0


def zoom_colour(rgb: np.ndarray, intr: Intrinsics, colour_focal: float) -> np.ndarray:
    """The colour image as a camera with the depth intrinsics would see it, for a colour camera of focal length
    `colour_focal` pixels with the same principal point (the small baseline between the two is ignored)."""
    import cv2

    sx, sy = colour_focal / intr.fx, colour_focal / intr.fy  # depth pixel cx + d is colour pixel cx + s d
    M = np.array([[sx, 0.0, intr.cx * (1 - sx)], [0.0, sy, intr.cy * (1 - sy)]])
    return cv2.warpAffine(rgb, M, (intr.width, intr.height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)


def overlap(points_world: np.ndarray, pose: np.ndarray, depth: np.ndarray, intr: Intrinsics,
            tolerance: float = 0.05) -> float:
    """Fraction of the points that the camera at `pose` sees where its depth image measured them."""
    p = points_world @ pose[:3, :3] - pose[:3, :3].T @ pose[:3, 3]  # world -> camera
    u, v = intr.project(torch.from_numpy(p))
    u, v = u.round().long().numpy(), v.round().long().numpy()
    inside = (p[:, 2] > 0) & (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)
    z = np.zeros(len(p))
    z[inside] = depth[v[inside], u[inside]]
    return float(np.mean(inside & (z > 0) & (np.abs(z - p[:, 2]) < tolerance * np.maximum(z, 1e-6))))


def pose_error(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    e = np.linalg.inv(truth) @ estimate
    return float(np.linalg.norm(e[:3, 3])), rotation_angle_deg(e[:3, :3])


def run(data: Path, kind: str, keyframe_every: int, query_every: int, min_overlap: float,
        cfg: RelocalizationConfig, colour_focal: float | None = None) -> dict:
    ds = open_dataset(data, kind)
    intr = ds.intrinsics

    def colour(rgb):
        return rgb if colour_focal is None else zoom_colour(rgb, intr, colour_focal)
    half = len(ds) // 2
    db = KeyframeDatabase(cfg)
    keyframes = []
    t0 = time.perf_counter()
    for i in range(0, half, keyframe_every):
        f = ds[i]
        if f.pose is None:
            continue
        db.add(i, colour(f.rgb), f.depth, f.pose, intr)
        keyframes.append((f.pose, f.depth))
    add_s = (time.perf_counter() - t0) / max(len(keyframes), 1)

    rows = []
    for i in range(half, len(ds), query_every):
        f = ds[i]
        if f.pose is None:
            continue
        pts = backproject(f.depth, intr, f.pose, stride=8)
        seen = max(overlap(pts, pose, depth, intr) for pose, depth in keyframes)
        rgb = colour(f.rgb)
        t, cpu = time.perf_counter(), time.process_time()
        r = db.relocalize(rgb, f.depth, intr)
        row = {"frame": i, "overlap": seen, "seconds": time.perf_counter() - t, "cpu_s": time.process_time() - cpu,
               "found": r is not None}
        if r is not None:
            row.update(zip(("error_m", "error_deg"), pose_error(r.pose, f.pose)))
            row.update(keyframe=r.keyframe_id, inliers=r.inliers, matches=r.matches)
        rows.append(row)
        print(json.dumps(row), file=sys.stderr)

    black = np.zeros((intr.height, intr.width, 3), np.uint8)
    t = time.process_time()
    covered = db.relocalize(black, np.zeros((intr.height, intr.width), np.float32), intr)
    covered_s = time.process_time() - t

    def within(r, metres, degrees):
        return r["found"] and r["error_m"] < metres and r["error_deg"] < degrees

    def recall(rows_, metres, degrees):
        return round(sum(within(r, metres, degrees) for r in rows_) / max(len(rows_), 1), 3)

    sees = [r for r in rows if r["overlap"] >= min_overlap]
    found = [r for r in rows if r["found"]]
    coarse = [r for r in found if within(r, COARSE_M, COARSE_DEG)]
    times = np.array([r["seconds"] for r in rows[1:]])  # the first query also builds the vocabulary
    cpu = np.array([r["cpu_s"] for r in rows[1:]])
    lost = np.array([r["cpu_s"] for r in rows[1:] if not r["found"]])
    return {
        "data": str(data), "colour_focal": colour_focal, "keyframes": len(keyframes), "queries": len(rows),
        "queries_seeing_map": len(sees), "recall_5cm_5deg": recall(sees, CORRECT_M, CORRECT_DEG),
        "recall_10cm_10deg": recall(sees, COARSE_M, COARSE_DEG),
        "relocalized_not_seeing_map": sum(within(r, COARSE_M, COARSE_DEG) for r in rows if r["overlap"] < min_overlap),
        "returned": len(found), "wrong": len(found) - len(coarse),
        # pose errors of the relocalized queries that are not wrong (within 10 cm / 10 degrees)
        "error_cm_median": 100 * float(np.median([r["error_m"] for r in coarse])) if coarse else None,
        "error_cm_max": 100 * float(np.max([r["error_m"] for r in coarse])) if coarse else None,
        "error_deg_median": float(np.median([r["error_deg"] for r in coarse])) if coarse else None,
        "error_deg_max": float(np.max([r["error_deg"] for r in coarse])) if coarse else None,
        "query_ms_median": 1000 * float(np.median(times)), "query_ms_max": 1000 * float(np.max(times)),
        "query_cpu_ms_median": 1000 * float(np.median(cpu)), "query_cpu_ms_max": 1000 * float(np.max(cpu)),
        "not_found_cpu_ms_median": 1000 * float(np.median(lost)) if len(lost) else None,
        "first_query_ms": 1000 * rows[0]["seconds"] if rows else None,
        "covered_lens_cpu_ms": 1000 * covered_s, "covered_lens_found": covered is not None,
        "add_keyframe_ms": 1000 * add_s,
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--kind", default="auto", help="data set kind (icl for ICL-NUIM: its poses need the y flip)")
    p.add_argument("--keyframe-every", type=int, default=10)
    p.add_argument("--query-every", type=int, default=5)
    p.add_argument("--min-overlap", type=float, default=0.3)
    p.add_argument("--colour-focal", type=float, help="register colour to depth first (7-Scenes: 525)")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                   help="RelocalizationConfig fields, e.g. candidates=5 ratio=0.75")
    p.add_argument("--json", type=Path, help="also write the summary here")
    args = p.parse_args()
    cfg = RelocalizationConfig()
    for item in args.set:
        key, value = item.split("=", 1)
        if not hasattr(cfg, key):
            p.error(f"unknown RelocalizationConfig field {key!r}")
        setattr(cfg, key, type(getattr(cfg, key))(value))
    cv2_threads()
    summary = run(args.data, args.kind, args.keyframe_every, args.query_every, args.min_overlap, cfg,
                  args.colour_focal)
    print(json.dumps(summary, indent=1))
    if args.json:
        args.json.write_text(json.dumps(summary, indent=1))
    return 0


def cv2_threads() -> None:
    """OpenCV's own thread pool competes with torch's for the cores; the relocalizer runs in the tracker's thread."""
    import cv2

    cv2.setNumThreads(1)


if __name__ == "__main__":
    sys.exit(main())
