"""Accuracy of both presets on rendered and real RGB-D data: ATE, drift, depth consistency, speed, in one table.

    python bench/accuracy.py                                   # all four runs, all frames (long: about an hour)
    python bench/accuracy.py --frames 0:20 --out runs/acc20    # a quick check
    python bench/accuracy.py --datasets 7scenes --presets fast,open3d

Runs, each with the existing command line (`python -m eslam_core run ...` in its own process, then `eslam eval`'s
`evaluate_run` on its output):
- `fast` through the two-process runtime (`--workers 2`), the live preset;
- `paper`: the paper's settings in lock-step (`--workers 1`): the `icl` preset on ICL-NUIM, and on 7-Scenes the same
  Replica settings with 7-Scenes' reader and ICL's tracking border (`replica` + dataset.kind=7scenes,
  tracking.border=20), since the paper has no 7-Scenes configuration;
on ../shared/data/icl_office_kt0 (rendered, `dataset.kind=icl`) and ../shared/data/7scenes_redkitchen_0_399 (real
Kinect v1). The preset `open3d` adds the classical peer (bench/open3d_peer.py, stock Open3D dense SLAM) on the same
frames.

Columns: ATE RMSE (rigid alignment), RPE per metre travelled (translation; needs >= 1 m of reference path), the
depth consistency score (median |depth residual| of frame pairs warped into each other, and the share within 3 cm;
see eslam_core/mapping/consistency.py) of the estimated poses and of the reference poses on the same pairs,
seconds per frame (the whole run, warm-up included, as `eslam run` reports it). Writes OUT/accuracy.md (the table)
and OUT/accuracy.json (every figure of every run, with the command lines and the machine's load average).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from eslam_core.cli import parse_frames  # noqa: E402
from eslam_core.evaluation.report import evaluate_run, write_report_json  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
DATASETS = {
    "icl": {"path": DATA / "icl_office_kt0", "kind": "icl", "label": "ICL-NUIM office kt0 (rendered)"},
    "7scenes": {"path": DATA / "7scenes_redkitchen_0_399", "kind": "7scenes",
                "label": "7-Scenes RedKitchen (real Kinect v1)"},
}
# (config, --set overrides, workers) per data set and preset
PRESETS = {
    "fast": {"icl": ("fast", ["dataset.kind=icl"], 2), "7scenes": ("fast", ["dataset.kind=7scenes"], 2)},
    "paper": {"icl": ("icl", [], 1),
              "7scenes": ("replica", ["dataset.kind=7scenes", "tracking.border=20"], 1)},
}


def frames_text(frames: tuple) -> str:
    start, stop = frames
    return f"{start}:{'' if stop is None else stop}"


def run_eslam(data: dict, preset: str, config: str, sets: list[str], workers: int, frames: tuple,
              out: Path) -> dict:
    """`eslam run` of one preset in its own process; returns the command and its wall time."""
    command = [sys.executable, "-m", "eslam_core", "run", "--config", config, "--data", str(data["path"]),
               "--out", str(out), "--frames", frames_text(frames), "--workers", str(workers), "--no-mesh", "-q"]
    for item in sets:
        command += ["--set", item]
    started = time.perf_counter()
    subprocess.run(command, check=True, cwd=ROOT)
    return {"command": " ".join(command), "wall_seconds": time.perf_counter() - started}


def run_open3d(data: dict, frames: tuple, out: Path, open3d_python: str) -> dict:
    command = [sys.executable, str(ROOT / "bench" / "open3d_peer.py"), "--data", str(data["path"]), "--kind",
               data["kind"], "--out", str(out), "--frames", frames_text(frames), "--open3d-python", open3d_python]
    started = time.perf_counter()
    subprocess.run(command, check=True, cwd=ROOT)
    return {"command": " ".join(command), "wall_seconds": time.perf_counter() - started}


def figures(report: dict, summary: dict) -> dict:
    """The table's figures of one evaluated run (None where not measured)."""
    trajectory = report.get("trajectory") or {}
    per_metre = trajectory.get("rpe_per_metre") or {}
    consistency = report.get("consistency") or {}
    estimate, reference = consistency.get("estimate") or {}, consistency.get("reference") or {}
    return {
        "frames": summary.get("n_frames"),
        "ate_rmse_cm": trajectory.get("ate_rmse_cm"),
        "rpe_per_metre_cm": per_metre.get("trans_rmse_cm"),
        "rpe_per_metre_deg": per_metre.get("rot_rmse_deg"),
        "consistency_estimate_mm": estimate.get("median_mm"),
        "agree_estimate_percent": estimate.get("agree_percent"),
        "consistency_reference_mm": reference.get("median_mm"),
        "agree_reference_percent": reference.get("agree_percent"),
        "consistency_pairs": estimate.get("pairs"),
        "seconds_per_frame": summary.get("seconds_per_frame"),
    }


def _cell(value: Optional[float], digits: int, unit: str = "") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    return f"{value:.{digits}f}{unit}"


def render_table(rows: list[dict]) -> str:
    header = ["data set", "method", "frames", "ATE RMSE", "RPE / m", "consistency: estimate",
              "consistency: reference", "s / frame"]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for row in rows:
        f = row["figures"]
        lines.append("| " + " | ".join([
            row["dataset"], row["method"], str(f["frames"]),
            _cell(f["ate_rmse_cm"], 2, " cm"),
            f"{_cell(f['rpe_per_metre_cm'], 2, ' cm')} / {_cell(f['rpe_per_metre_deg'], 2, '°')}",
            f"{_cell(f['consistency_estimate_mm'], 1, ' mm')} ({_cell(f['agree_estimate_percent'], 1, ' %')})",
            f"{_cell(f['consistency_reference_mm'], 1, ' mm')} ({_cell(f['agree_reference_percent'], 1, ' %')})",
            _cell(f["seconds_per_frame"], 3),
        ]) + " |")
    return "\n".join(lines) + ("\n\nConsistency: median |depth residual| of frame pairs warped into each other with "
                               "the poses (share of pixels within 3 cm); the reference poses are scored on the same "
                               "pairs. RPE / m: translation / rotation error per metre travelled.\n")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "accuracy", help="folder for the runs")
    parser.add_argument("--frames", type=parse_frames, default=(0, None), help="A:B, frames of every run")
    parser.add_argument("--datasets", default="icl,7scenes", help="comma-separated: icl, 7scenes")
    parser.add_argument("--presets", default="fast,paper", help="comma-separated: fast, paper, open3d")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="an extra config override for every eslam run (repeatable)")
    parser.add_argument("--open3d-python", default="/work/o3d-venv/bin/python",
                        help="a Python with open3d, for the open3d preset")
    parser.add_argument("--consistency-frames", type=int, default=100,
                        help="frames of the depth consistency score, evenly spread (default 100)")
    args = parser.parse_args(argv)

    datasets = [d.strip() for d in args.datasets.split(",") if d.strip()]
    presets = [p.strip() for p in args.presets.split(",") if p.strip()]
    for name, known in ((datasets, DATASETS), (presets, [*PRESETS, "open3d"])):
        unknown = sorted(set(name) - set(known))
        if unknown:
            parser.error(f"unknown {', '.join(unknown)}: choose from {', '.join(known)}")
    args.out.mkdir(parents=True, exist_ok=True)

    rows = []
    for dataset_name in datasets:
        data = DATASETS[dataset_name]
        if not data["path"].is_dir():
            parser.error(f"data set {data['path']} not found (see ../shared/data/README.md)")
        jobs = [(p, *PRESETS[p][dataset_name]) if p in PRESETS else (p, None, [], None) for p in presets]
        for preset, config, sets, workers in jobs:
            out = args.out / f"{dataset_name}-{preset}"
            load_before = os.getloadavg()
            if preset == "open3d":
                ran = run_open3d(data, args.frames, out, args.open3d_python)
                method = "Open3D dense SLAM (peer)"
            else:
                ran = run_eslam(data, preset, config, sets + args.set, workers, args.frames, out)
                method = f"{preset} (`--config {config}`, {'two processes' if workers == 2 else 'lock-step'})"
            report = evaluate_run(out, depth_views=0, consistency_frames=args.consistency_frames)
            write_report_json(report, out / "report.json")
            summary = json.loads((out / "summary.json").read_text())
            rows.append({"dataset": data["label"], "method": method, "run_dir": str(out),
                         "figures": figures(report, summary), **ran,
                         "load_average_before": load_before, "load_average_after": os.getloadavg()})
            print(f"{dataset_name} {preset}: {json.dumps(rows[-1]['figures'])}", flush=True)

    table = render_table(rows)
    (args.out / "accuracy.md").write_text(table)
    (args.out / "accuracy.json").write_text(json.dumps({"frames": list(args.frames), "rows": rows}, indent=2))
    print()
    print(table)
    print(f"(written to {args.out / 'accuracy.md'} and {args.out / 'accuracy.json'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
