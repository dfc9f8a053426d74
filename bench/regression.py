"""Real-data regression guard (the last stage of .ci/run): short runs on ../shared/data, each held to a bound.

    python bench/regression.py [--data ../shared/data] [--out bench_regression.json]

- ICL-NUIM office, frames 0:100, `fast` through the two processes (`eslam run --workers 2`): ATE, frames/s;
- 7-Scenes RedKitchen, frames 0:100, the same: ATE, frames/s;
- the node's live replay (`bench/ros_replay.py`, node defaults: `live`, live policy) of ICL frames 0:300 (10 s at
  30 Hz): poses published, latency, ATE of the published poses.

Each figure has a bound set from measured runs with room for a loaded CI machine (BOUNDS: the figures measured
and the bound beside them). Prints a table, writes JSON, exits 1 when a figure is out of bounds. Without the data
set folder (a user's machine) it says so and exits 0: the stage is skipped, not failed.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
ICL, KITCHEN = "icl_office_kt0", "7scenes_redkitchen_0_399"

# (bound, the direction that is worse). Measured on the 2-core development machine, session 27, three runs (README,
# "Real-data regression stage"): ICL 100 frames 0.227-0.237 cm at 13.6-17.1 frames/s (the warm-up included);
# 7-Scenes 100 frames 1.639-1.652 cm at 12.8-14.1 frames/s; the 10 s ICL replay 298-299 of 300 frames posed,
# latency median 29-34 ms, ATE 0.24-0.27 cm.
BOUNDS = {
    "icl_ate_cm": (0.4, "max"),
    # Frames/s follow the machine's speed: 13.6-17.1 and 12.8-14.1 measured on the development machine, but on
    # 2026-12-07 the same machine ran everything 1.6-1.9x slower (the suite 27 min instead of 14) and the commit
    # before that day's changes gave 8.9 / 9.3 on ICL, the changes 9.3 / 9.6. The bounds catch a collapse (half the
    # usual speed), not a slower machine.
    "icl_frames_per_s": (7.0, "min"),
    "kitchen_ate_cm": (2.5, "max"),
    "kitchen_frames_per_s": (6.0, "min"),
    # The replay on that slower day, 16 runs of each of two commits: 259-297 of 300 frames posed, latency median
    # 33.5-53.8 ms (README, "The system layer redesign, measured"): the bounds were 0.9 and 60 ms until then.
    "replay_posed_fraction": (0.8, "min"),
    "replay_latency_median_ms": (80.0, "max"),
    "replay_ate_cm": (0.6, "max"),
}


def offline_run(data: Path, kind: str, work: Path) -> dict:
    """`eslam run` of frames 0:100 with `fast` through the two processes; its summary.json."""
    out = work / kind
    command = [sys.executable, "-m", "eslam_core", "run", "--config", "fast", "--workers", "2", "--no-mesh", "-q",
               "--data", str(data), "--set", f"dataset.kind={kind}", "--frames", "0:100", "--out", str(out)]
    done = subprocess.run(command, cwd=REPO, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"regression: `{' '.join(command)}` failed (exit {done.returncode}):\n{done.stderr[-3000:]}")
    return json.loads((out / "summary.json").read_text())


def live_replay(data: Path, work: Path) -> dict:
    """bench/ros_replay.py (node defaults) over ICL frames 0:300; its JSON."""
    out = work / "replay.json"
    command = [sys.executable, str(REPO / "bench" / "ros_replay.py"), "--data", str(data), "--kind", "icl",
               "--frames", "0:300", "--out", str(out)]
    done = subprocess.run(command, cwd=REPO, capture_output=True, text=True)
    if done.returncode != 0 or not out.is_file():
        raise SystemExit(f"regression: the node replay failed (exit {done.returncode}):\n{done.stdout[-3000:]}"
                         f"\n{done.stderr[-3000:]}")
    return json.loads(out.read_text())


def out_of_bounds(figures: dict) -> list[str]:
    """The figures beyond their bound, one line each (a missing figure counts as out)."""
    lines = []
    for name, (bound, worse) in BOUNDS.items():
        value = figures.get(name)
        if value is None or (value > bound if worse == "max" else value < bound):
            lines.append(f"{name} = {value} ({'at most' if worse == 'max' else 'at least'} {bound})")
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data", help="the data sets folder")
    ap.add_argument("--out", type=Path, default=Path("bench_regression.json"))
    args = ap.parse_args()
    missing = [name for name in (ICL, KITCHEN) if not (args.data / name).is_dir()]
    if missing:
        print(f"regression stage skipped: {', '.join(missing)} not in {args.data} (the data sets are on CI only)")
        return 0
    work = Path(tempfile.mkdtemp(prefix="eslam_regression_"))
    icl, kitchen = offline_run(args.data / ICL, "icl", work), offline_run(args.data / KITCHEN, "7scenes", work)
    replay = live_replay(args.data / ICL, work)
    latency = replay.get("latency_ms") or {}
    figures = {
        "icl_ate_cm": icl.get("ate_rmse_cm"),
        "icl_frames_per_s": 1.0 / icl["seconds_per_frame"] if icl.get("seconds_per_frame") else None,
        "kitchen_ate_cm": kitchen.get("ate_rmse_cm"),
        "kitchen_frames_per_s": 1.0 / kitchen["seconds_per_frame"] if kitchen.get("seconds_per_frame") else None,
        "replay_posed_fraction": replay["poses"] / replay["frames"] if replay.get("frames") else None,
        "replay_latency_median_ms": latency.get("median"),
        "replay_ate_cm": replay.get("ate_rmse_cm_of_published_poses"),
    }
    print(f"{'figure':28s} {'value':>9s}  bound")
    for name, (bound, worse) in BOUNDS.items():
        value = figures[name]
        shown = "-" if value is None else f"{value:.3f}"
        print(f"{name:28s} {shown:>9s}  {'<=' if worse == 'max' else '>='} {bound}")
    failures = out_of_bounds(figures)
    args.out.write_text(json.dumps({"figures": figures, "bounds": BOUNDS, "failures": failures}, indent=2))
    if failures:
        print("regression: out of bounds:\n  " + "\n  ".join(failures))
        return 1
    print(f"regression: every figure within its bound (-> {args.out})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
