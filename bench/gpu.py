"""ESLAM on a GPU against the paper's speed: the paper's settings on ICL-NUIM office kt0, lock-step and pipelined.

    python bench/gpu.py                              # checks, then both modes on all 300 frames (a few minutes)
    python bench/gpu.py --frames 0:40 --no-checks    # a quick look
    python bench/gpu.py --device cpu --frames 0:8    # the same script on the CPU (what a machine without a GPU can run)

Steps, each in its own process so that one failing does not take the others with it and every process's GPU
memory is its own:
1. `eslam doctor` and the device-agnostic tests on the GPU (`pytest test/test_device.py -k cuda`: lookup,
   rendering, mapping, tracking, the shared map through CUDA IPC), unless --no-checks;
2. `--config icl --set dataset.kind=icl` (the paper's settings at 640x480) through `run_sequence`, as `eslam run`
   runs it: lock-step (`--workers 1`) and pipelined (`--workers 2`, tracker and mapper processes sharing the map on
   the GPU), no mesh.
Prints one table: seconds per frame (the whole run, the 1000-iteration warm-up included, as `eslam run` reports
it), ATE RMSE, peak GPU memory (torch.cuda.max_memory_allocated of each process that held the map: the run's own,
and for the pipelined run the tracker's and the mapper's), next to the paper's 0.18 s per frame (RTX 3090) and our
CPU figures, and whether the targets hold (faster than the paper, ATE within 10 % of the CPU run). Writes
OUT/gpu.json and OUT/gpu.md.

On a lent device machine (no network, its own python3 with a CUDA torch, ../shared not sent, 64 MiB per call): the
sequence (135 MB) travels in parts, in calls close enough together that the machine stays warm, and the few
packages its image lacks (trimesh, rtree, embreex) as wheels (see the device tool's README):

    python bench/gpu.py --pack .gpu --part-mb 40          # here: .gpu/icl_1 ... icl_4, each under 40 MB
    # device calls, one after the other: carry [".gpu/icl_1"], then [".gpu/icl_2"], ...; the last one carries the
    # last part and .whl, installs the wheels to /tmp/site and runs
    PYTHONPATH=/tmp/site:. python3 bench/gpu.py --data .gpu/icl_1,.gpu/icl_2,.gpu/icl_3,.gpu/icl_4
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

DATA = ROOT.parent / "shared" / "data" / "icl_office_kt0"
PAPER_S_PER_FRAME = 0.18  # ESLAM paper, RTX 3090
# Ours on the 2-core development CPU, all 300 frames, `eslam run --config icl` (README, "Speed and accuracy").
CPU_LOCKSTEP = {"s_per_frame": 1.24, "ate_cm": 0.57}
MODES = {"lock-step": 1, "pipelined": 2}


def run_mode(args) -> dict:
    """One run in this process (the child side of main)."""
    import torch

    from eslam_core.cli import open_configured_dataset, parse_frames, parse_overrides
    from eslam_core.config import load_config
    from eslam_core.device import peak_memory_mb, resolve_device
    from eslam_core.runner import run_sequence

    frames = parse_frames(args.frames)
    cfg = load_config("icl", parse_overrides(["dataset.kind=icl", f"run.device={args.device}", *args.set]))
    device = resolve_device(cfg.run.device)
    ds = open_configured_dataset(cfg, Path(args.data), frames, 1)
    out = Path(args.out) / args.mode
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    start = time.perf_counter()
    s = run_sequence(cfg, ds, out, data_label=str(Path(args.data).resolve()), frames=(frames[0], frames[1], 1),
                     progress=False, write_mesh=False, workers=MODES[args.mode])
    wall = time.perf_counter() - start
    summary = json.loads((out / "summary.json").read_text())
    workers = summary.get("runtime", {}).get("workers_figures", {})
    gpu_mb = {"this process": peak_memory_mb(device)}
    if MODES[args.mode] == 2:
        gpu_mb.update(tracker=workers.get("tracker_device_peak_mb", 0.0), mapper=workers.get("mapper_device_peak_mb", 0.0))
    return {"mode": args.mode, "device": str(device), "frames": s.n_frames, "s_per_frame": s.seconds_per_frame,
            "wall_s": wall, "ate_cm": s.ate_rmse_cm, "peak_gpu_mb": gpu_mb, "peak_gpu_mb_total": sum(gpu_mb.values()),
            "peak_rss_mb": s.peak_memory_mb, "gpu": torch.cuda.get_device_name(device) if device.type == "cuda"
            else None, "torch": torch.__version__}


def child(args, mode: str, timeout: float) -> dict:
    cmd = [sys.executable, __file__, "--mode", mode, "--data", str(args.data), "--frames", args.frames,
           "--device", args.device, "--out", str(args.out)] + [x for s in args.set for x in ("--set", s)]
    print(f"[gpu.py] {mode}: {' '.join(cmd)}", flush=True)
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"mode": mode, "error": f"did not finish within {timeout:.0f} s"}
    sys.stderr.write(res.stderr[-4000:])
    lines = [line for line in res.stdout.splitlines() if line.startswith("RESULT ")]
    if res.returncode != 0 or not lines:
        return {"mode": mode, "error": f"exit {res.returncode}: {(res.stderr.strip().splitlines() or ['?'])[-1]}"}
    return json.loads(lines[-1][len("RESULT "):])


def checks(args) -> dict:
    """eslam doctor and the device tests; their output is printed as it is."""
    out = {}
    for name, cmd in (("doctor", [sys.executable, "-m", "eslam_core", "doctor"]),
                      ("device tests", [sys.executable, "-m", "pytest", "-q", "-x", "test/test_device.py"]
                       + (["-k", "cuda"] if args.device != "cpu" else []))):
        print(f"[gpu.py] {name}: {' '.join(cmd)}", flush=True)
        start = time.perf_counter()
        res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=args.timeout)
        print(res.stdout[-3000:] + res.stderr[-2000:], flush=True)
        out[name] = {"rc": res.returncode, "seconds": time.perf_counter() - start,
                     "tail": (res.stdout.strip().splitlines() or [""])[-1]}
    return out


def pack(data: Path, out: Path, part_mb: float) -> list[Path]:
    """Copy the sequence into parts of at most `part_mb` MB (the small text files in the first), for transfers
    with a size limit; `merged` puts them together again."""
    files = sorted(p for p in data.rglob("*") if p.is_file())
    parts: list[list[Path]] = [[]]
    size = 0
    for f in sorted(files, key=lambda f: (f.parent != data, str(f))):  # associations, ground truth first
        n = f.stat().st_size
        if parts[-1] and size + n > part_mb * 2**20:
            parts.append([])
            size = 0
        parts[-1].append(f)
        size += n
    folders = []
    for k, members in enumerate(parts, 1):
        folder = out / f"icl_{k}"
        for f in members:
            target = folder / f.relative_to(data)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(f, target)
        folders.append(folder)
        print(f"{folder}: {len(members)} files, {sum(f.stat().st_size for f in members) / 2**20:.1f} MB")
    return folders


def merged(parts: list[Path]) -> Path:
    """One folder of links to the files of every part (the parts of `pack`, or a single folder as it is)."""
    if len(parts) == 1:
        return parts[0]
    root = Path(tempfile.mkdtemp(prefix="icl_"))
    for part in parts:
        for f in part.rglob("*"):
            if f.is_file():
                target = root / f.relative_to(part)
                target.parent.mkdir(parents=True, exist_ok=True)
                target.symlink_to(f.resolve())
    return root


def cell(v, fmt: str, unit: str = "") -> str:
    return "n/a" if v is None else format(v, fmt) + unit


def table(results: list[dict]) -> str:
    rows = ["| run | seconds per frame | ATE RMSE | peak GPU memory |", "|---|---|---|---|",
            f"| paper (RTX 3090) | {PAPER_S_PER_FRAME:.2f} | | |",
            f"| ours, CPU lock-step (2 cores, README) | {CPU_LOCKSTEP['s_per_frame']:.2f} | "
            f"{CPU_LOCKSTEP['ate_cm']:.2f} cm | |"]
    for r in results:
        if "error" in r:
            rows.append(f"| ours, {r['mode']} | failed: {r['error']} | | |")
            continue
        parts = ", ".join(f"{k} {v:.0f}" for k, v in r["peak_gpu_mb"].items())
        rows.append(f"| ours, {r['device']} {r['mode']} ({r['frames']} frames) | {r['s_per_frame']:.3f} | "
                    f"{cell(r['ate_cm'], '.2f', ' cm')} | {r['peak_gpu_mb_total']:.0f} MB ({parts}) |")
    verdicts = []
    for r in results:
        if "error" in r or r["ate_cm"] is None:
            continue
        faster = r["s_per_frame"] < PAPER_S_PER_FRAME
        within = r["ate_cm"] <= 1.1 * CPU_LOCKSTEP["ate_cm"]
        verdicts.append(f"- {r['mode']}: {'faster' if faster else 'slower'} than the paper's "
                        f"{PAPER_S_PER_FRAME} s/frame ({r['s_per_frame'] / PAPER_S_PER_FRAME:.2f}x its time); ATE "
                        f"{'within' if within else 'NOT within'} 10 % of the CPU run's {CPU_LOCKSTEP['ate_cm']} cm "
                        f"({r['ate_cm'] / CPU_LOCKSTEP['ate_cm']:.2f}x)")
    return "\n".join(rows + [""] + verdicts)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", default=str(DATA), help=f"ICL-NUIM office kt0 in TUM layout, or the comma-separated "
                   f"parts made by --pack (default {DATA})")
    p.add_argument("--pack", type=Path, metavar="DIR", help="only split --data into parts under DIR, then exit")
    p.add_argument("--part-mb", type=float, default=40.0, help="--pack: MB per part (default 40)")
    p.add_argument("--frames", default="0:", help="A:B, frames to run (default all 300)")
    p.add_argument("--device", default="cuda", help="run.device for the runs (default cuda)")
    p.add_argument("--modes", default="lock-step,pipelined", help="comma-separated: lock-step, pipelined")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="extra config overrides")
    p.add_argument("--out", type=Path, default=Path(os.environ.get("OUT", "runs/gpu")), help="output folder "
                   "(default $OUT or runs/gpu)")
    p.add_argument("--timeout", type=float, default=420.0, help="seconds allowed per step (default 420)")
    p.add_argument("--no-checks", action="store_true", help="skip eslam doctor and the device tests")
    p.add_argument("--mode", choices=sorted(MODES), help=argparse.SUPPRESS)  # internal: one run in this process
    args = p.parse_args()
    if args.mode:
        print("RESULT " + json.dumps(run_mode(args)), flush=True)
        return 0
    if args.pack:
        pack(Path(args.data), args.pack, args.part_mb)
        return 0
    args.data = merged([Path(d) for d in args.data.split(",")])
    if not (args.data / "associations.txt").exists():
        print(f"gpu.py: no ICL-NUIM sequence at {args.data} (associations.txt missing): pass --data", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    report = {"checks": checks(args) if not args.no_checks else {}, "runs": []}
    for mode in args.modes.split(","):
        report["runs"].append(child(args, mode.strip(), args.timeout))
        print(f"[gpu.py] {json.dumps(report['runs'][-1])}", flush=True)
    text = table(report["runs"])
    print(text)
    (args.out / "gpu.md").write_text(text + "\n")
    (args.out / "gpu.json").write_text(json.dumps(report, indent=2))
    return 0 if all("error" not in r for r in report["runs"]) else 1


if __name__ == "__main__":
    sys.exit(main())
