"""Throughput of the pipelined runtime (tracker and mapper processes) against the lock-step schedule, same frames.

    python bench/runtime.py --data ../shared/data/icl_office_kt0 [--frames 0:60]
    python bench/runtime.py                     # the synthetic room (generated) with the demo preset

Both modes run the same preset (icl for ICL-NUIM data) on the same frames, in one invocation, each in its own
process (so that peak memory is the mode's own): "lockstep" is the single-process schedule (`--workers 1`: tracking
and mapping alternate, torch using every core), "pipelined" the two-process runtime (`--workers 2`, offline policy:
every frame, in order; one torch thread per worker on a 2-core machine).

Timing: frames are read into memory first. Frame 0 (the map's warm-up) is timed on its own, until the first map
the tracker gets (pipelined with `runtime.first_map_after`, as in `fast`: part way through the warm-up, whose rest
then counts in the throughput); throughput is then measured from there until every remaining frame is tracked and
every keyframe mapped. The whole-run time is reported too. The machine's load average is recorded before and after each
run: on a shared machine use --repeats (runs alternate between the modes) and compare runs taken under the same
load. OMP_WAIT_POLICY from the environment applies to both modes (the runtime's workers default to PASSIVE).
Prints a table (frames/s, s/frame, ATE RMSE, peak memory) and the pipelined/lock-step throughput ratio; writes JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from eslam_core.cli import open_configured_dataset, parse_frames, parse_overrides  # noqa: E402
from eslam_core.config import RuntimeConfig, load_config  # noqa: E402
from eslam_core.evaluation.trajectory_error import ate  # noqa: E402
from eslam_core.trajectory import Trajectory  # noqa: E402
from eslam_core.runtime import make_runtime  # noqa: E402
from eslam_core.runtime.shared import stage_profile  # noqa: E402

MODES = {"lockstep": 1, "pipelined": 2}


def wait_until(condition, what: str, timeout: float = 7200.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"gave up waiting for {what} after {timeout:.0f} s")
        time.sleep(0.02)


def run_mode(mode: str, cfg, frames: list, intrinsics, threads: int, options: dict) -> dict:
    """One mode on the preloaded frames; returns its timings, accuracy and memory."""
    workers = MODES[mode]
    torch.manual_seed(cfg.run.seed)
    rt = make_runtime(cfg, intrinsics, workers=workers, policy="offline", threads=threads, **options)
    t0 = time.perf_counter()
    rt.start()
    started = time.perf_counter()
    rt.submit(frames[0])
    if workers == 1:  # the lock-step step of frame 0 returns after its warm-up
        wait_until(lambda: rt.health().frames_tracked >= 1, "the warm-up")
    else:
        wait_until(lambda: rt.health().map_version >= 1, "the warm-up")
    warm = time.perf_counter()
    for f in frames[1:]:
        rt.submit(f)
        rt.poll()

    def finished() -> bool:
        h = rt.health()
        return h.frames_tracked >= len(frames) and h.keyframe_queue_depth == 0

    wait_until(finished, "the run to finish")
    done = time.perf_counter()
    health = rt.health()
    rt.close()
    closed = time.perf_counter()
    timestamps, poses = rt.trajectory()
    gt = [(f.timestamp, f.pose) for f in frames if f.pose is not None]
    rmse = None
    if len(gt) >= 3:
        truth = Trajectory(np.array([t for t, _ in gt]), np.stack([p for _, p in gt]))
        rmse = 100.0 * ate(Trajectory(timestamps, poses), truth, max_dt=1e-6).rmse
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    figures = rt.worker_figures() if workers == 2 else {}
    steady = len(frames) - 1
    return {
        "mode": mode,
        "workers": workers,
        "torch_threads": threads,  # per process
        "options": options,
        "frames": len(frames),
        "startup_s": started - t0,
        "warmup_s": warm - started,
        "steady_s": done - warm,
        "steady_frames_per_s": steady / (done - warm),
        "steady_s_per_frame": (done - warm) / steady,
        "total_s": done - started,
        "close_s": closed - done,
        "ate_rmse_cm": rmse,
        "peak_memory_mb": own + figures.get("tracker_peak_mb", 0.0) + figures.get("mapper_peak_mb", 0.0),
        "peak_memory_by_process_mb": {"parent": own, "tracker": figures.get("tracker_peak_mb"),
                                      "mapper": figures.get("mapper_peak_mb")} if workers == 2 else {"process": own},
        "health": health.as_dict(),
        "stages": stage_profile(figures) if workers == 2 else [],
        "wall_s_after_warm_up": done - warm,
    }


def child(args) -> int:
    """Run one mode (in a process of its own) and print its JSON."""
    cfg = load_config(args.config, parse_overrides(args.set))
    ds = open_configured_dataset(cfg, args.data, args.frames, 1)
    frames = [ds[i] for i in range(len(ds))]
    cores = len(os.sched_getaffinity(0))
    # Per process: lock-step has the whole machine, each pipelined worker its share of it.
    threads = (args.lockstep_threads or cores) if args.mode == "lockstep" else (args.threads or max(1, cores // 2))
    options = {}
    if args.mode == "pipelined":
        options = {"lend_threads": not args.no_lend, "keyframe_backlog": args.keyframe_backlog,
                   "publish_every": args.publish_every, "catch_up_iterations": args.catch_up_iterations}
    result = run_mode(args.mode, cfg, frames, ds.intrinsics, threads, options)
    print("RESULT " + json.dumps(result), flush=True)
    return 0


def run_child(args, mode: str) -> Optional[dict]:
    """One mode in a process of its own (its own peak memory); None if it failed."""
    load_before = os.getloadavg()
    cmd = [sys.executable, __file__, "--mode", mode, "--data", str(Path(args.data).resolve()), "--config", args.config,
           "--frames", f"{args.frames[0]}:{'' if args.frames[1] is None else args.frames[1]}",
           "--threads", str(args.threads), "--lockstep-threads", str(args.lockstep_threads)]
    if args.keyframe_backlog is not None:
        cmd += ["--keyframe-backlog", str(args.keyframe_backlog)]
    if args.catch_up_iterations is not None:
        cmd += ["--catch-up-iterations", str(args.catch_up_iterations)]
    if args.no_lend:
        cmd += ["--no-lend"]
    cmd += ["--publish-every", str(args.publish_every)]
    for s in args.set:
        cmd += ["--set", s]
    print(f"running {mode} ...", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    if proc.returncode != 0 or not lines:
        print(proc.stderr[-4000:], file=sys.stderr)
        print(f"{mode} failed (exit code {proc.returncode})", file=sys.stderr)
        return None
    result = json.loads(lines[-1][len("RESULT "):])
    result["load_average_before"] = load_before
    result["load_average_after"] = os.getloadavg()
    return result


def synthetic_room(size: str, n: int) -> Path:
    from eslam_core.demo import default_cache, parse_size
    from eslam_core.datasets.synthetic import ensure_scene

    w, h = parse_size(size)
    return ensure_scene(default_cache(), n_frames=n, width=w, height=h, seed=0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, help="data set folder (default: the synthetic room, generated and cached)")
    ap.add_argument("--config", default=None, help="preset or YAML (default: icl with --data, demo without)")
    ap.add_argument("--frames", type=parse_frames, default=(0, 60), help="A:B, frames to run (default 0:60)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config value")
    ap.add_argument("--threads", type=int, default=0, help="torch threads per worker (default: cores / 2)")
    ap.add_argument("--lockstep-threads", type=int, default=0, help="torch threads of lock-step (default: cores)")
    ap.add_argument("--modes", default="lockstep,pipelined", help="comma-separated: lockstep, pipelined")
    ap.add_argument("--keyframe-backlog", type=int, default=None,
                    help="pipelined: keyframes that may wait before older ones are merged into the newest one's "
                         "mapping step (default: none merged, every keyframe gets its step as in lock-step)")
    ap.add_argument("--catch-up-iterations", type=int, default=None,
                    help="pipelined: once newer keyframes wait, a mapping step ends after this many iterations "
                         "divided by their number (default: never, every step runs all its iterations as in "
                         "lock-step)")
    ap.add_argument("--no-lend", action="store_true", help="pipelined: an idle worker keeps its threads")
    ap.add_argument("--publish-every", type=int, default=RuntimeConfig.publish_every,
                    help="pipelined: mapping iterations between mid-step map publications (default: that of "
                         "runtime.publish_every, 0 = the tracker sees only maps at the end of a step)")
    ap.add_argument("--repeats", type=int, default=1, help="runs per mode, in alternating order (medians reported)")
    ap.add_argument("--size", default="320x240", help="synthetic room image size (without --data)")
    ap.add_argument("--out", type=Path, default=Path("bench_runtime.json"), help="JSON results file")
    ap.add_argument("--mode", choices=tuple(MODES), help=argparse.SUPPRESS)  # internal: run one mode
    args = ap.parse_args()
    if args.config is None:
        args.config = "icl" if args.data is not None else "demo"
    if args.data is None:
        args.data = synthetic_room(args.size, args.frames[1] or 60)
    if args.mode:
        return child(args)

    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    unknown = [m for m in modes if m not in MODES]
    if unknown:
        ap.error(f"unknown mode(s) {unknown}: choose from {', '.join(MODES)}")
    results = {"data": str(Path(args.data).resolve()), "config": args.config, "overrides": args.set,
               "frames": list(args.frames), "cores": len(os.sched_getaffinity(0)),
               "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "(unset: libgomp default)"),
               "runs": {m: [] for m in modes}}
    # Alternate the order (A B, B A, ...) so that a drift of the machine's load hits both modes alike.
    for repeat in range(args.repeats):
        for mode in (modes if repeat % 2 == 0 else modes[::-1]):
            result = run_child(args, mode)
            if result is None:
                return 1
            results["runs"][mode].append(result)

    print()
    print(f"{'mode':<10} {'frames/s':>9} {'s/frame':>8} {'warm-up s':>9} {'total s':>8} {'ATE cm':>7} "
          f"{'peak MB':>8} {'threads':>7} {'load 1m':>8}")
    for mode, runs in results["runs"].items():
        for r in runs:
            ate_text = "n/a" if r["ate_rmse_cm"] is None else f"{r['ate_rmse_cm']:.2f}"
            print(f"{mode:<10} {r['steady_frames_per_s']:>9.3f} {r['steady_s_per_frame']:>8.2f} "
                  f"{r['warmup_s']:>9.1f} {r['total_s']:>8.1f} {ate_text:>7} {r['peak_memory_mb']:>8.0f} "
                  f"{r['torch_threads']:>7} {r['load_average_before'][0]:>8.2f}")
    for r in results["runs"].get("pipelined", []):
        print("\nper-stage profile of a pipelined run (ms per event; share of the wall time after the warm-up):")
        for row in r["stages"]:
            print(f"  {row['stage']:<50} {row['ms']:>8.1f} ms per {row['per']:<14} "
                  f"{100 * row['total_s'] / r['wall_s_after_warm_up']:>5.1f} %")
    if {"lockstep", "pipelined"} <= set(results["runs"]):
        def median(mode: str, key: str) -> Optional[float]:
            values = [r[key] for r in results["runs"][mode] if r[key] is not None]
            return float(np.median(values)) if values else None

        ratio = median("pipelined", "steady_frames_per_s") / median("lockstep", "steady_frames_per_s")
        results["throughput_ratio"] = ratio
        results["throughput_ratio_total"] = median("lockstep", "total_s") / median("pipelined", "total_s")
        print(f"\npipelined / lock-step throughput after the warm-up (medians of {args.repeats} run(s) each): "
              f"{ratio:.2f}x (whole run incl. warm-up: {results['throughput_ratio_total']:.2f}x; target >= 1.5x)")
        ate_ls, ate_pl = median("lockstep", "ate_rmse_cm"), median("pipelined", "ate_rmse_cm")
        if ate_ls is not None and ate_pl is not None:
            results["ate_ratio"] = ate_pl / ate_ls
            print(f"ATE pipelined / lock-step: {results['ate_ratio']:.2f} (target <= 1.2)")
    args.out.write_text(json.dumps(results, indent=2))
    print(f"results -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
