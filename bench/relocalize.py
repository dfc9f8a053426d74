"""Relocalization benchmark: lost and found with ESLAM, and the place recognition alone.

    python bench/relocalize.py --data ../shared/data/icl_office_kt0 --kind icl --scenario slam
    python bench/relocalize.py --data ../shared/data/7scenes_redkitchen_0_399 --scenario slam
    python bench/relocalize.py --data ../shared/data/icl_office_kt0 --kind icl          # database only

`--scenario slam` (the issue's benchmark): ESLAM (lock-step, `--config`, default the `fast` preset) maps the first
half of the sequence and saves its checkpoint; then
  (a) the same run goes on over the second half with every `--blank-every`th frame blanked (black image, no depth,
      as a covered lens). Each blank is an *event*: detected when that frame is lost; found at the first later
      frame that is not lost. Reported: detection rate, recall (events found within 10 frames / events; the frames
      after a blank see the map, the run has just mapped them), frames and seconds to relocalize, the pose error
      at the found frame (next to the error of the frame before the blank: the run's drift), the cost per frame
      while lost, and frames lost outside any event (false alarms on unblanked frames);
  (b) for each of `--starts` (fractions of the sequence), the checkpoint is loaded in localization mode and fed
      `--window` frames from there: the first frames are lost until relocalized. Reported: frames and seconds to
      relocalize, recall (frames not lost / frames that see the map, by the overlap rule below), the pose error
      of the found frames, the cost per frame while lost and per tracked frame, and that the map is unchanged.
Pose errors are against the reference poses (the map's frame is the first frame's reference pose).

`--scenario database` (default): the place recognition and PnP alone. The database holds every `--keyframe-every`th frame of the first half of the sequence, at its reference pose; the
queries are every `--query-every`th frame of the second half. A query *sees the map* when at least
`--min-overlap` of its depth points (at its reference pose) are seen by some keyframe at the depth that keyframe
measured (a view of the same things from the other side of the room counts: it is in the map, although no feature
matcher finds it). Reported: recall (queries relocalized within 5 cm / 5 degrees, and within 10 cm / 10 degrees,
over those that see the map), wrong poses (returned but off by more than 10 cm or 10 degrees: the dangerous kind),
pose error of the relocalized ones, time per query (ORB extraction included; wall clock and CPU, OpenCV on one
thread: on a shared machine the CPU time is the steadier figure), and a query on a frame with a covered lens
(black, no depth).

7-Scenes colour is registered to depth by the reader (`dataset.register_colour`, on by default; as shipped, the
database scenario found 17 % of the queries within 10 cm / 10 degrees, and 63 % with the colour resampled).
`--as-shipped` keeps the colour unregistered.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from eslam_core.camera import Frame, Intrinsics, backproject  # noqa: E402
from eslam_core.cli import open_configured_dataset, parse_frames, parse_overrides  # noqa: E402
from eslam_core.config import load_config  # noqa: E402
from eslam_core.datasets import open_dataset  # noqa: E402
from eslam_core.geometry import rotation_angle_deg  # noqa: E402
from eslam_core.tracking.relocalization import KeyframeDatabase, RelocalizationConfig  # noqa: E402

CORRECT_M, CORRECT_DEG = 0.05, 5.0
COARSE_M, COARSE_DEG = 0.10, 10.0


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
        cfg: RelocalizationConfig, register_colour: bool = True) -> dict:
    ds = open_dataset(data, kind, register_colour=register_colour)
    intr = ds.intrinsics
    half = len(ds) // 2
    db = KeyframeDatabase(cfg)
    keyframes = []
    t0 = time.perf_counter()
    for i in range(0, half, keyframe_every):
        f = ds[i]
        if f.pose is None:
            continue
        db.add(i, f.rgb, f.depth, f.pose, intr)
        keyframes.append((f.pose, f.depth))
    add_s = (time.perf_counter() - t0) / max(len(keyframes), 1)

    rows = []
    for i in range(half, len(ds), query_every):
        f = ds[i]
        if f.pose is None:
            continue
        pts = backproject(f.depth, intr, f.pose, stride=8)
        seen = max(overlap(pts, pose, depth, intr) for pose, depth in keyframes)
        rgb = f.rgb
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
        "data": str(data), "register_colour": register_colour, "keyframes": len(keyframes), "queries": len(rows),
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


# ================================================================================================= ESLAM scenario

FOUND_WITHIN = 10  # frames: the recovery bound


def blanked(frame: Frame) -> Frame:
    """A covered lens: a black image and no depth (the reference pose stays, for the error figures)."""
    return dataclasses.replace(frame, rgb=np.zeros_like(frame.rgb), depth=np.zeros_like(frame.depth))


def stepped(slam, frame: Frame) -> dict:
    t, cpu = time.perf_counter(), time.process_time()
    r = slam.step(frame)
    return {"frame": frame.index, "lost": bool(r.lost), "seconds": time.perf_counter() - t,
            "cpu_s": time.process_time() - cpu, "_pose": r.pose, "_truth": frame.pose}


def map_to_reference(rows: list[dict]) -> np.ndarray:
    """The rigid transform from the map's frame to the reference poses': the mean over the mapped frames of
    reference @ inverse(estimate) (rotations averaged by projecting their sum onto SO(3)). The map starts at the
    first frame's reference pose when it has one, which ICL's first frame has not."""
    offsets = [r["_truth"] @ np.linalg.inv(r["_pose"]) for r in rows if r["_truth"] is not None]
    u, _, vt = np.linalg.svd(sum(o[:3, :3] for o in offsets))
    transform = np.eye(4)
    transform[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    transform[:3, 3] = np.mean([o[:3, 3] for o in offsets], axis=0)
    return transform


def with_errors(rows: list[dict], alignment: np.ndarray) -> list[dict]:
    """The rows with their pose error against the reference (in its frame), the poses themselves dropped."""
    out = []
    for r in rows:
        row = {k: v for k, v in r.items() if not k.startswith("_")}
        if r["_truth"] is not None:
            row["error_m"], row["error_deg"] = pose_error(alignment @ r["_pose"], r["_truth"])
        out.append(row)
    return out


def _median_ms(values) -> float | None:
    return round(1000 * float(np.median(values)), 1) if len(values) else None


def _cm(values) -> dict:
    return {"median": round(100 * float(np.median(values)), 2), "max": round(100 * float(np.max(values)), 2)} \
        if len(values) else None


def blank_events(rows: list[dict], blank: set[int]) -> dict:
    """Part (a) figures from the per-frame rows of the second half."""
    position = {r["frame"]: k for k, r in enumerate(rows)}
    events, in_event = [], set()
    for b in sorted(blank):
        k = position[b]
        found = next((j for j in range(k + 1, len(rows)) if not rows[j]["lost"]), None)
        in_event.update(rows[j]["frame"] for j in range(k, found if found is not None else len(rows)))
        event = {"blank": b, "detected": rows[k]["lost"], "found_after_frames": None if found is None else found - k,
                 "error_before_m": rows[k - 1].get("error_m") if k > 0 else None}
        if found is not None and "error_m" in rows[found]:
            event["error_m"], event["error_deg"] = rows[found]["error_m"], rows[found]["error_deg"]
            event["seconds_to_found"] = sum(r["seconds"] for r in rows[k + 1:found + 1])
        events.append(event)
        print(json.dumps(event), file=sys.stderr)
    found = [e for e in events if e["found_after_frames"] is not None and e["found_after_frames"] <= FOUND_WITHIN
             and "error_m" in e]
    lost_rows = [r for r in rows if r["lost"]]
    false_lost = [r["frame"] for r in lost_rows if r["frame"] not in in_event]
    return {
        "events": len(events), "detected": sum(e["detected"] for e in events),
        "recall_within_10_frames": round(len(found) / max(len(events), 1), 3),
        "frames_to_found_max": max((e["found_after_frames"] for e in found), default=None),
        "seconds_to_found_median": round(float(np.median([e["seconds_to_found"] for e in found])), 3)
        if found else None,
        "error_cm_at_found": _cm([e["error_m"] for e in found]),
        "error_deg_at_found_max": round(max(e["error_deg"] for e in found), 2) if found else None,
        "error_cm_before_blank": _cm([e["error_before_m"] for e in found if e["error_before_m"] is not None]),
        "lost_frame_cpu_ms_median": _median_ms([r["cpu_s"] for r in lost_rows]),
        "tracked_frame_cpu_ms_median": _median_ms([r["cpu_s"] for r in rows if not r["lost"]]),
        "false_lost_frames": false_lost,
    }


def localization_run(checkpoint: Path, cfg, ds, start: int, window: int, keyframe_views,
                     alignment: np.ndarray) -> dict:
    """Part (b): the saved map in localization mode, from frame `start` on."""
    from eslam_core.slam import loaded_slam

    slam = loaded_slam(checkpoint, cfg, ds.intrinsics)
    before = {k: v.clone() for k, v in slam.map.field.state_dict().items()}
    rows = []
    for i in range(start, min(start + window, len(ds))):
        f = ds[i]
        row = stepped(slam, f)
        pts = backproject(f.depth, ds.intrinsics, f.pose, stride=8)
        row["overlap"] = max(overlap(pts, pose, depth, ds.intrinsics) for pose, depth in keyframe_views)
        rows.append(row)
    rows = with_errors(rows, alignment)
    for row in rows:
        print(json.dumps(row), file=sys.stderr)
    unchanged = all(torch.equal(before[k], v) for k, v in slam.map.field.state_dict().items())
    first = next((k for k, r in enumerate(rows) if not r["lost"]), None)
    sees = [r for r in rows if r["overlap"] >= 0.3]
    tracked = [r for r in rows if not r["lost"] and "error_m" in r]
    return {
        "start": start, "frames": len(rows), "frames_seeing_map": len(sees),
        "frames_to_found": first, "seconds_to_found": round(sum(r["seconds"] for r in rows[:first + 1]), 3)
        if first is not None else None,
        "recall": round(sum(not r["lost"] for r in sees) / max(len(sees), 1), 3),
        "lost_after_found": sum(r["lost"] for r in rows[first:]) if first is not None else None,
        "error_cm_tracked": _cm([r["error_m"] for r in tracked]),
        "error_deg_tracked_max": round(max(r["error_deg"] for r in tracked), 2) if tracked else None,
        "lost_frame_cpu_ms_median": _median_ms([r["cpu_s"] for r in rows if r["lost"]]),
        "tracked_frame_ms_median": _median_ms([r["seconds"] for r in tracked]),
        "map_unchanged": unchanged,
    }


def run_slam_scenario(data: Path, config: str, sets: list[str], blank_every: int, starts: list[float],
                      window: int, frames: tuple = (0, None)) -> dict:
    from eslam_core.outputs.export import save_checkpoint
    from eslam_core.slam import SLAM

    cfg = load_config(config, parse_overrides(sets))
    ds = open_configured_dataset(cfg, data, frames, 1)
    half = len(ds) // 2
    slam = SLAM(cfg, ds.intrinsics)
    t = time.perf_counter()
    mapped = [stepped(slam, ds[i]) for i in range(half)]
    map_s = time.perf_counter() - t
    alignment = map_to_reference(mapped)
    mapped = with_errors(mapped, alignment)
    workdir = Path(tempfile.mkdtemp(prefix="relocalize_"))
    checkpoint = save_checkpoint(slam, workdir / "checkpoint.pt")
    summary = {"data": str(data), "config": config, "set": sets, "frames": len(ds), "mapped_frames": half,
               "map_seconds_per_frame": round(map_s / half, 3),
               "map_ate_cm": round(100 * float(np.sqrt(np.mean([r["error_m"] ** 2 for r in mapped if "error_m" in r]))), 2),
               "keyframes": len(slam.map.keyframes)}

    blank = set(range(half + blank_every - 1, len(ds) - 1, blank_every))  # a blank needs a frame after it
    rows = with_errors([stepped(slam, blanked(ds[i]) if i in blank else ds[i]) for i in range(half, len(ds))],
                       alignment)
    summary["blanked"] = blank_events(rows, blank)

    keyframe_views = [(f.pose, f.depth) for f in (ds[i] for i in range(0, half, 10)) if f.pose is not None]
    localization = load_config(config, parse_overrides(sets + ["run.mode=localization"]))
    summary["localization"] = [localization_run(checkpoint, localization, ds, int(fraction * len(ds)), window,
                                                keyframe_views, alignment) for fraction in starts]
    return summary


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--scenario", choices=("database", "slam"), default="database")
    p.add_argument("--config", default="fast", help="slam scenario: preset or YAML file")
    p.add_argument("--config-set", nargs="*", default=[], metavar="KEY=VALUE", help="slam scenario: overrides")
    p.add_argument("--blank-every", type=int, default=30)
    p.add_argument("--starts", type=float, nargs="*", default=[0.6, 0.75, 0.9],
                   help="slam scenario: where localization restarts, as fractions of the sequence")
    p.add_argument("--window", type=int, default=30, help="slam scenario: frames fed from each restart")
    p.add_argument("--frames", type=parse_frames, default=(0, None), help="slam scenario: A:B, the frames used")
    p.add_argument("--kind", default="auto", help="data set kind (icl for ICL-NUIM: its poses need the y flip)")
    p.add_argument("--keyframe-every", type=int, default=10)
    p.add_argument("--query-every", type=int, default=5)
    p.add_argument("--min-overlap", type=float, default=0.3)
    p.add_argument("--as-shipped", action="store_true", help="database scenario: 7-Scenes colour unregistered")
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
    if args.scenario == "slam":
        sets = args.config_set + ([] if args.kind == "auto" else [f"dataset.kind={args.kind}"])
        summary = run_slam_scenario(args.data, args.config, sets, args.blank_every, args.starts, args.window,
                                    args.frames)
        print(json.dumps(summary, indent=1))
        if args.json:
            args.json.write_text(json.dumps(summary, indent=1))
        return 0
    summary = run(args.data, args.kind, args.keyframe_every, args.query_every, args.min_overlap, cfg,
                  not args.as_shipped)
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
