"""Spaces larger than a room: accuracy of the trajectory and of the mesh, memory and speed on the generated flat,
corridor loop and two-storey scenes (eslam_core/datasets/large_scenes.py), with the synthetic room as the
single-room reference.

    python bench/submaps.py                                  # every scene (generated once, cached)
    python bench/submaps.py --scenes corridor_loop --frames 0:400 --out runs/submaps-quick
    python bench/submaps.py --scenes flat --sensor ideal     # exact depth at any range: the tracker's part apart

Each run is `python -m eslam_core run` in its own process (the command is in the JSON), then `eslam eval`'s
`evaluate_run` against the scene's true mesh: ATE RMSE, mesh accuracy, completion and completion ratio (< 5 cm),
both meshes culled to what the cameras saw. Also the run's peak memory, the feature planes' bytes, seconds per
frame, and the end of the walk: how far the last pose is from the truth (the drift a loop closure would remove).
Writes OUT/submaps.md and OUT/submaps.json.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from eslam_core.cli import parse_frames  # noqa: E402
from eslam_core.datasets.large_scenes import SCENES, generate_large_scene  # noqa: E402
from eslam_core.datasets.synthetic import SensorModel, ensure_scene  # noqa: E402
from eslam_core.evaluation.report import evaluate_run, write_report_json  # noqa: E402
from eslam_core.datasets.tum import read_tum  # noqa: E402

CACHE = Path(os.environ.get("ESLAM_CACHE", Path.home() / ".cache" / "eslam")) / "large"


# The generated scenes' sensor: Kinect-like (the default) or ideal (exact depth at any range, no noise): the second
# separates what the submaps and loops do from what the sensor's range and noise do to the tracker.
SENSORS = {"kinect": SensorModel(), "ideal": SensorModel.ideal()}


def revisit_to_corrected(summary: dict) -> tuple:
    """Frames and seconds of input from the first loop's keyframe (the camera back where an older submap mapped)
    to the frame that first had the map corrected by it; Nones without a loop."""
    closures = summary.get("loop_closures") or []
    if not closures:
        return None, None
    first = closures[0]
    return float(first["corrected"] - first["revisit"]), first.get("seconds")


def scene_folder(name: str, width: int, height: int, sensor: str = "kinect") -> Path:
    """The generated scene (once: later runs reuse it)."""
    if name == "room":
        return ensure_scene(CACHE.parent, n_frames=300, width=width, height=height, sensor=SENSORS[sensor])
    folder = CACHE / (f"{name}-{width}x{height}" + ("" if sensor == "kinect" else f"-{sensor}"))
    if not (folder / "scene.json").is_file():
        partial = folder.with_name(folder.name + ".partial")
        if partial.exists():
            shutil.rmtree(partial)
        started = time.perf_counter()
        generate_large_scene(partial, name, width, height, sensor=SENSORS[sensor])
        partial.rename(folder)
        print(f"generated {name}: {time.perf_counter() - started:.0f} s", flush=True)
    return folder


def end_drift_cm(run_dir: Path) -> float:
    """Distance between the last estimated camera and its true position (in the run's own frame: its first pose is
    the true one), in cm."""
    estimate, truth = read_tum(run_dir / "trajectory.txt"), read_tum(run_dir / "groundtruth.txt")
    last = int(np.argmin(np.abs(truth.timestamps - estimate.timestamps[-1])))
    return float(100 * np.linalg.norm(estimate.poses[-1][:3, 3] - truth.poses[last][:3, 3]))


def quality_profile(run_dir: Path) -> dict:
    """How the run's poses said they were (pose_quality.csv): the share of frames lost and degraded, the first
    lost frame, and the longest run of degraded frames (no keyframe is made there: the map stops growing)."""
    q = np.genfromtxt(run_dir / "pose_quality.csv", delimiter=",", names=True)
    lost, degraded = q["lost"] > 0, q["degraded"] > 0
    longest = run = 0
    for d in degraded:
        run = run + 1 if d else 0
        longest = max(longest, run)
    return {"lost_percent": 100 * float(lost.mean()), "degraded_percent": 100 * float(degraded.mean()),
            "first_lost": int(np.argmax(lost)) if lost.any() else None, "longest_degraded_run": longest}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(("room",) + SCENES),
                        help=f"comma-separated: room (the single-room reference), {', '.join(SCENES)}")
    parser.add_argument("--config", default="fast")
    parser.add_argument("--workers", type=int, default=1, help="1: lock-step; 2: the two-process runtime")
    parser.add_argument("--frames", type=parse_frames, default=(0, None))
    parser.add_argument("--size", default="320x240", help="image size of the generated scenes")
    parser.add_argument("--sensor", choices=sorted(SENSORS), default="kinect",
                        help="the generated scenes' sensor: kinect (range 0.3-5 m, noise, holes) or ideal")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "submaps")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.split("x"))
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    unknown = sorted(set(scenes) - {"room", *SCENES})
    if unknown:
        parser.error(f"unknown scene {', '.join(unknown)}: choose from room, {', '.join(SCENES)}")
    args.out.mkdir(parents=True, exist_ok=True)

    rows = []
    for name in scenes:
        data = scene_folder(name, width, height, args.sensor)
        out = args.out / name
        start, stop = args.frames
        command = [sys.executable, "-m", "eslam_core", "run", "--config", args.config, "--data", str(data), "--out",
                   str(out), "--frames", f"{start}:{'' if stop is None else stop}", "--workers", str(args.workers),
                   "--set", "dataset.kind=tum", "-q"] + [f"--set={s}" for s in args.set]
        started = time.perf_counter()
        subprocess.run(command, check=True, cwd=ROOT)
        wall = time.perf_counter() - started
        report = evaluate_run(out, depth_views=0, plots=False, consistency_frames=0)
        write_report_json(report, out / "report.json")
        summary = json.loads((out / "summary.json").read_text())
        mesh = report.get("reconstruction") or {}
        row = {"scene": name, "frames": summary["n_frames"],
               "path_m": json.loads((data / "scene.json").read_text()).get("large_scene", {}).get("path_m"),
               "ate_cm": (report.get("trajectory") or {}).get("ate_rmse_cm"), "end_drift_cm": end_drift_cm(out),
               "accuracy_cm": mesh.get("accuracy_cm"), "completion_cm": mesh.get("completion_cm"),
               "completion_ratio_percent": mesh.get("completion_ratio_percent"),
               "map_mb": summary["parameter_count"] * 4 / 2**20, "peak_memory_mb": summary["peak_memory_mb"],
               "seconds_per_frame": summary["seconds_per_frame"], "submaps": summary.get("submaps", 1),
               "loops": summary.get("loops_closed"), "revisit_to_corrected": revisit_to_corrected(summary)[0],
               "revisit_to_corrected_s": revisit_to_corrected(summary)[1],
               **quality_profile(out), "command": " ".join(command),
               "wall_seconds": wall}
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "command"}), flush=True)

    def cell(value, digits: int) -> str:
        return "–" if value is None or (isinstance(value, float) and not math.isfinite(value)) else \
            f"{value:.{digits}f}"

    header = ["scene", "frames", "path (m)", "ATE (cm)", "end drift (cm)", "accuracy (cm)", "completion (cm)",
              "completion < 5 cm (%)", "planes (MB)", "peak memory (MB)", "s / frame", "submaps", "loops",
              "revisit to corrected (frames / s)",
              "lost (%)", "degraded (%)", "first lost", "longest degraded run"]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for r in rows:
        lines.append("| " + " | ".join([r["scene"], str(r["frames"]), cell(r["path_m"], 1), cell(r["ate_cm"], 2),
                                        cell(r["end_drift_cm"], 1), cell(r["accuracy_cm"], 2),
                                        cell(r["completion_cm"], 2), cell(r["completion_ratio_percent"], 1),
                                        cell(r["map_mb"], 1), cell(r["peak_memory_mb"], 0),
                                        cell(r["seconds_per_frame"], 3), str(r["submaps"]),
                                        "–" if r["loops"] is None else str(r["loops"]),
                                        cell(r["revisit_to_corrected"], 0) + " / " +
                                        cell(r["revisit_to_corrected_s"], 2),
                                        cell(r["lost_percent"], 1), cell(r["degraded_percent"], 1),
                                        "–" if r["first_lost"] is None else str(r["first_lost"]),
                                        str(r["longest_degraded_run"])]) + " |")
    table = "\n".join(lines) + "\n"
    (args.out / "submaps.md").write_text(table)
    (args.out / "submaps.json").write_text(json.dumps({"config": args.config, "workers": args.workers, "sensor": args.sensor,
                                                       "rows": rows}, indent=2))
    print()
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
