"""Two node settings compared by live replays, run in turn: pose rate and latency of each, and their ratio.

    python bench/replay_pairs.py --data ../shared/data/icl_office_kt0 --kind icl --pairs 8 \
        --a mesh_period=2.0 --b mesh_period=0.0

One replay's p99 is its third-worst frame of 300, and it moves by 15-20 % from run to run on 2 cores; so the
settings alternate (A, B, A, B, ...: a change of machine load touches both alike), each run is listed, and the
comparison is made on the frames of all runs of a setting pooled. Each run is `bench/ros_replay.py`; its JSON is
kept in --out-dir. Run it alone on the machine: anything else running skews both settings.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
PERCENTILES = (50, 90, 99)


def replay(args, params: list[str], out: Path) -> dict:
    command = [sys.executable, str(HERE / "ros_replay.py"), "--out", str(out)]
    if args.data is not None:
        command += ["--data", str(args.data), "--kind", args.kind]
    for param in params:
        command += ["--param", param]
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    return json.loads(out.read_text())


def pooled(runs: list[dict]) -> dict:
    latency_ms = 1000 * np.concatenate([list(r["latency_s_by_stamp"].values()) for r in runs])
    figures = {f"p{q}_ms": float(np.percentile(latency_ms, q)) for q in PERCENTILES}
    figures["poses_per_run"] = float(np.mean([r["poses"] for r in runs]))
    return figures


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, help="data set folder (default: ros_replay.py's synthetic room)")
    ap.add_argument("--kind", default="auto")
    ap.add_argument("--pairs", type=int, default=5)
    ap.add_argument("--a", action="append", default=[], metavar="NAME=VALUE", help="node parameter of setting A")
    ap.add_argument("--b", action="append", default=[], metavar="NAME=VALUE", help="node parameter of setting B")
    ap.add_argument("--out-dir", type=Path, default=Path("bench_replay_pairs"))
    args = ap.parse_args()
    args.out_dir.mkdir(parents=True, exist_ok=True)

    runs: dict[str, list[dict]] = {"A": [], "B": []}
    print(f"A: {' '.join(args.a) or 'defaults'}; B: {' '.join(args.b) or 'defaults'}")
    print(f"{'run':<6}{'poses':>7}{'median ms':>11}{'p90 ms':>8}{'p99 ms':>8}{'ATE cm':>8}")
    for pair in range(args.pairs):
        for name, params in (("A", args.a), ("B", args.b)):
            r = replay(args, params, args.out_dir / f"{name}{pair}.json")
            runs[name].append(r)
            lat, ate = r["latency_ms"] or {}, r["ate_rmse_cm_of_published_poses"]
            print(f"{name}{pair:<5}{r['poses']:>7}{lat.get('median', float('nan')):>11.0f}"
                  f"{lat.get('p90', float('nan')):>8.0f}{lat.get('p99', float('nan')):>8.0f}"
                  f"{ate if ate is not None else float('nan'):>8.2f}", flush=True)
    a, b = pooled(runs["A"]), pooled(runs["B"])
    print(f"\npooled over {args.pairs} runs each:")
    print(f"{'':<16}{'A':>9}{'B':>9}{'A / B':>8}")
    for key in a:
        print(f"{key:<16}{a[key]:>9.1f}{b[key]:>9.1f}{a[key] / b[key]:>8.2f}")
    (args.out_dir / "pooled.json").write_text(json.dumps({"A": args.a, "B": args.b, "pooled_A": a, "pooled_B": b},
                                                         indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
