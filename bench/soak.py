"""Soak: hours of a camera in the same space, compressed. A sequence is played forward, then backward, again and
again (monotonic stamps at 30 Hz) through the pipelined runtime; memory must stop growing once the space is
explored, and accuracy must not decay.

    python bench/soak.py --data ../shared/data/icl_office_kt0 --kind icl --minutes 20
    python bench/soak.py --minutes 2          # the synthetic room (generated), quick

Every `--every` seconds it prints the resident memory of each process (parent, tracker, mapper), the keyframes
kept, and the bytes of the map and the keyframe store; after each lap the lap's ATE (RMSE against ground truth
over that lap's frames, rigidly aligned) and how many of its frames were tracked (the live policy drops the frames
the tracker is too slow for). Every `--interval` seconds of input it takes the workers' per-stage profile of that
interval (ms per event) and the latency of its poses; at the end the first and the last interval side by side:
whatever costs more per frame after an hour than after a minute grows with the run's length. Targets (an hour
live): every lap tracks >= 99 % of its frames, memory from the end of lap 2 to the end grows < 10 %, the worst
lap's ATE <= 1.2x the first's, the last interval's profile within 10 % of the first's. Writes JSON.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from eslam_core.camera import Frame  # noqa: E402
from eslam_core.cli import parse_overrides  # noqa: E402
from eslam_core.config import load_config  # noqa: E402
from eslam_core.datasets import open_dataset  # noqa: E402
from eslam_core.evaluation.trajectory_error import ate  # noqa: E402
from eslam_core.trajectory import Trajectory  # noqa: E402
from eslam_core.cpu import freeze_start_up_objects  # noqa: E402
from eslam_core.runtime import make_runtime  # noqa: E402
from eslam_core.runtime.shared import stage_profile  # noqa: E402

FPS = 30.0


def memory_mb(pid: int) -> dict[str, float]:
    """Resident memory of a process (MB): in all, and its anonymous (heap) and shared-memory parts (Linux)."""
    out = {"rss": float("nan"), "anon": float("nan"), "shmem": float("nan")}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key = {"VmRSS:": "rss", "RssAnon:": "anon", "RssShmem:": "shmem"}.get(line.split(maxsplit=1)[0])
            if key:
                out[key] = int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return out


def process_counters(pid: int) -> dict[str, float]:
    """A process's CPU seconds (user + system), page faults (minor, major) and context switches (voluntary: it
    waited; involuntary: the scheduler took the core away) so far (Linux): what a stage that got slower spent its
    time on, or waited for."""
    out = {}
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        tick = os.sysconf("SC_CLK_TCK")
        out.update(cpu_s=(int(fields[11]) + int(fields[12])) / tick, minor_faults=int(fields[7]),
                   major_faults=int(fields[9]))
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            name, _, value = line.partition(":")
            if name in ("voluntary_ctxt_switches", "nonvoluntary_ctxt_switches"):
                out[name.split("_")[0]] = int(value)
    except (OSError, IndexError, ValueError):
        pass
    return out


def machine_counters() -> dict[str, float]:
    """The machine's CPU time stolen by the hypervisor (seconds, all cores; /proc/stat): a virtual machine whose
    host takes cycles away runs every process slower without any of them doing more work."""
    try:
        fields = Path("/proc/stat").read_text().splitlines()[0].split()
        return {"steal_s": int(fields[8]) / os.sysconf("SC_CLK_TCK")}
    except (OSError, IndexError, ValueError):
        return {}


PROBE_EVERY = 150  # frames (5 s of input): 120 probes in ten minutes, 0.2 % of a core


def speed_probe_ms() -> float:
    """CPU time of a fixed piece of work (numpy and plain Python, about 10 ms): if it costs more late in the run,
    the machine got slower, not the workers' work larger."""
    a = np.arange(40_000, dtype=np.float64).reshape(200, 200) / 40_000
    t = time.thread_time()
    for _ in range(10):
        a = np.tanh(a @ a.T / 200)
    sum(i * i for i in range(50_000))
    return (time.thread_time() - t) * 1000


def rss_mb(pid: int) -> float:
    return memory_mb(pid)["rss"]


def lap_order(n: int, lap: int) -> range:
    return range(n) if lap % 2 == 0 else range(n - 1, -1, -1)


def interval_rows(intervals: list, latency: np.ndarray, i: int, baseline: dict) -> dict:
    """Interval i's per-stage profile (ms per event over the interval: the difference of the counters at its two
    ends), each process's counters per frame, and the latency of the poses of the frames played in it. `baseline`:
    the counters when the first interval began."""
    start = intervals[i - 1] if i > 0 else baseline
    end = intervals[i]
    delta = {name: value - start["counters"].get(name, 0.0) for name, value in end["counters"].items()}
    frames = max(end["frames"] - start["frames"], 1)
    processes = {name: {key: (value - start["processes"].get(name, {}).get(key, 0.0)) / frames
                        for key, value in counters.items()} for name, counters in end.get("processes", {}).items()}
    lat = latency[start["frames"]:end["frames"]]
    lat = lat[np.isfinite(lat)]
    return {"interval": i + 1, "frames": end["frames"] - start["frames"], "poses": len(lat),
            "latency_ms_median": float(np.median(lat) * 1000) if len(lat) else float("nan"),
            "latency_ms_p90": float(np.percentile(lat, 90) * 1000) if len(lat) else float("nan"),
            "stages": {row["stage"]: row["ms"] for row in stage_profile(delta)},
            "processes_per_frame": processes,
            "speed_probe_ms": float(np.median(end["probe_ms"])) if end.get("probe_ms") else float("nan")}


def print_intervals(first: dict, last: dict, seconds: float) -> None:
    print(f"\nper-stage profile, ms per event: the first and the last interval of {seconds / 60:.0f} minutes of input")
    print(f"  {'':<52} {'first':>8} {'last':>8}  last/first")
    for stage, a in first["stages"].items():
        b = last["stages"].get(stage, float("nan"))
        ratio = b / a if a > 0 else float("nan")
        print(f"  {stage:<52} {a:8.2f} {b:8.2f}  {ratio:6.2f}")
    for key, label in (("latency_ms_median", "latency, median (ms)"), ("latency_ms_p90", "latency, p90 (ms)")):
        print(f"  {label:<52} {first[key]:8.1f} {last[key]:8.1f}  {last[key] / first[key]:6.2f}")
    print(f"  {'speed probe: fixed work, CPU ms (the machine)':<52} {first['speed_probe_ms']:8.2f} "
          f"{last['speed_probe_ms']:8.2f}  {last['speed_probe_ms'] / first['speed_probe_ms']:6.2f}")
    print(f"  {'poses / frames played':<52} {first['poses'] / max(first['frames'], 1):8.3f} "
          f"{last['poses'] / max(last['frames'], 1):8.3f}")
    for name, counters in first["processes_per_frame"].items():
        for key, label, scale in (("cpu_s", "CPU ms a frame", 1000), ("minor_faults", "page faults a frame", 1),
                                  ("nonvoluntary", "cores taken away a frame", 1), ("voluntary", "waits a frame", 1),
                                  ("steal_s", "CPU ms stolen by the host a frame", 1000)):
            if key not in counters:
                continue
            a = counters.get(key, float("nan")) * scale
            b = last["processes_per_frame"][name].get(key, float("nan")) * scale
            print(f"  {name + ': ' + label:<52} {a:8.2f} {b:8.2f}  {b / a if a > 0 else float('nan'):6.2f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None, help="a data set folder (default: the synthetic room, generated)")
    ap.add_argument("--kind", default="auto")
    ap.add_argument("--config", default="fast")
    ap.add_argument("--set", action="append", default=[], help="config override KEY=VALUE")
    ap.add_argument("--minutes", type=float, default=20.0, help="minutes of 30 Hz input to play")
    ap.add_argument("--every", type=float, default=30.0, help="seconds between memory reports")
    ap.add_argument("--interval", type=float, default=600.0,
                    help="seconds of input per profile interval (first and last compared at the end)")
    ap.add_argument("--policy", choices=("offline", "live"), default="offline",
                    help="offline: every frame, as fast as SLAM goes; live: frames at 30 Hz of wall time, the "
                         "tracker skips to the newest frame beyond runtime.live_backlog waiting (the ROS node's default)")
    ap.add_argument("--out", default="runs/soak.json")
    args = ap.parse_args()

    if args.data is None:
        from eslam_core.datasets.synthetic import ensure_scene

        root = ensure_scene(Path(os.environ.get("ESLAM_CACHE", Path.home() / ".cache" / "eslam")), n_frames=120)
        ds = open_dataset(root, "tum")
    else:
        ds = open_dataset(Path(args.data), args.kind)
    cfg = load_config(args.config, {"dataset": {"kind": ds.kind}, **parse_overrides(args.set)})
    frames = [ds[i] for i in range(len(ds))]  # in memory: the soak measures SLAM, not the disk
    n, total = len(frames), int(args.minutes * 60 * FPS)
    laps = math.ceil(total / n)
    print(f"{n} frames x {laps} laps = {laps * n} frames ({laps * n / FPS / 60:.1f} min of 30 Hz input), "
          f"config {args.config}, pipelined runtime, {args.policy} policy", flush=True)

    rt = make_runtime(cfg, ds.intrinsics, workers=2, policy=args.policy)
    rt.start()
    freeze_start_up_objects()  # (as slam_node does: cpu.py)
    pids = {"parent": os.getpid(), **rt.resources()["pids"]}

    def counters() -> dict:
        return {**{name: process_counters(pid) for name, pid in pids.items()}, "machine": machine_counters()}

    baseline = {"frames": 0, "counters": {}, "processes": counters()}
    probes: list = []  # the speed probe's figures since the last interval closed
    samples, lap_ends = [], []
    # Per frame played, in arrays (this process's memory is measured too): the pose as tracked, the latency (NaN:
    # no pose), the data set's frame.
    posed = np.zeros((total, 4, 4), np.float32)
    latency = np.full(total, np.nan, np.float32)
    source = np.zeros(total, np.int32)
    truth = ds.gt_poses()
    start = last_report = time.monotonic()

    def report(label: str) -> dict:
        figures = rt.worker_figures()
        sample = {"t_s": time.monotonic() - start, "label": label, "tracked": rt.health().frames_tracked,
                  **{f"rss_mb_{k}": rss_mb(p) for k, p in pids.items()},
                  "memory_mb": {k: memory_mb(p) for k, p in pids.items()},
                  "keyframes_kept": int(figures.get("keyframes_kept", 0)),
                  "map_mb": figures.get("map_bytes", 0.0) / 2**20,
                  "keyframe_mb": figures.get("keyframe_bytes", 0.0) / 2**20}
        sample["rss_mb_total"] = sum(v for k, v in sample.items() if k.startswith("rss_mb_") and math.isfinite(v))
        # (a process's RSS counts the shared map and frame ring it has touched: the anonymous part is its own heap)
        samples.append(sample)
        print(f"{sample['t_s']:7.0f} s  {label:>8}  frames {sample['tracked']:6d}  RSS parent "
              f"{sample['rss_mb_parent']:6.0f}  tracker {sample['rss_mb_tracker']:6.0f}  mapper "
              f"{sample['rss_mb_mapper']:6.0f}  total {sample['rss_mb_total']:6.0f} MB  keyframes "
              f"{sample['keyframes_kept']:5d}  map {sample['map_mb']:6.1f} MB  keyframe store "
              f"{sample['keyframe_mb']:6.1f} MB", flush=True)
        return sample

    lap_ate: list = []
    laps_out: list = []  # per lap: frames played, tracked, ATE
    intervals: list = []  # per interval of input: the workers' counters at its end, the frames played by then

    def collect() -> None:
        for u in rt.poll():
            posed[u.index], latency[u.index] = u.pose, u.latency_s

    def close_interval() -> None:
        intervals.append({"frames": k, "counters": rt.worker_figures(), "processes": counters(),
                          "probe_ms": probes[:]})
        probes.clear()
        first = interval_rows(intervals, latency, 0, baseline)
        last = interval_rows(intervals, latency, len(intervals) - 1, baseline)
        print(f"interval {len(intervals)} (to frame {k}): {last['latency_ms_median']:.1f} ms median latency, "
              f"{last['poses']} poses of {last['frames']} frames; tracker "
              f"{last['stages'].get('tracker: front end (tracking)', float('nan')):.1f} ms a frame (interval 1: "
              f"{first['stages'].get('tracker: front end (tracking)', float('nan')):.1f})", flush=True)

    def score_lap(lap: int) -> None:
        """The lap's ATE from the poses as tracked (printed while the soak goes on)."""
        first = lap_ends[lap - 1] if lap else 0
        posed_here = [j for j in range(first, lap_ends[lap]) if np.isfinite(latency[j])]
        # (ICL's first frame has no reference pose: tracked, it counts, but not in the ATE)
        sel = [j for j in posed_here if truth[source[j]] is not None]
        if len(sel) < 3:
            return
        t = np.array(sel, dtype=np.float64) / FPS
        err = ate(Trajectory(t, posed[sel].astype(np.float64)),
                  Trajectory(t, np.stack([truth[source[j]] for j in sel])), max_dt=1e-6).rmse
        lap_ate.append(100.0 * err)
        played = lap_ends[lap] - first
        # (which of the data set's frames went without a pose: the same ones lap after lap point at a cause)
        missed = [int(source[j]) for j in range(first, lap_ends[lap]) if not np.isfinite(latency[j])]
        laps_out.append({"lap": lap + 1, "played": played, "tracked": len(posed_here), "ate_cm": lap_ate[-1],
                         "missed": missed})
        print(f"lap {lap + 1:3d}: ATE {lap_ate[-1]:.2f} cm, {len(posed_here)} of {played} frames tracked"
              + (f" (without a pose: frames {', '.join(map(str, missed[:8]))}{' ...' if len(missed) > 8 else ''})"
                 if missed else ""), flush=True)

    k = 0
    next_interval = args.interval * FPS
    for lap in range(laps):
        for i in lap_order(n, lap):
            if k >= total:
                break
            f = frames[i]
            if args.policy == "live":  # as a camera delivers them
                time.sleep(max(0.0, start + k / FPS - time.monotonic()))
            rt.submit(Frame(k, k / FPS, f.rgb, f.depth, f.pose))
            source[k] = i
            k += 1
            collect()
            if k % PROBE_EVERY == 0:
                probes.append(speed_probe_ms())
            if time.monotonic() - last_report >= args.every:
                last_report = time.monotonic()
                report("")
            if k >= next_interval:
                next_interval += args.interval * FPS
                close_interval()
        lap_ends.append(k)
        if lap >= 1:
            score_lap(lap - 1)  # its frames are tracked by now, except a few still queued
    while True:  # every frame tracked (or dropped by the live policy) and every keyframe mapped
        h = rt.health()
        if h.frames_tracked + h.frames_dropped >= k and h.input_queue_depth == 0 and h.keyframe_queue_depth == 0:
            break
        collect()
        time.sleep(0.1)
    final = report("end")
    collect()
    score_lap(len(lap_ends) - 1)
    if not intervals or intervals[-1]["frames"] < k:
        close_interval()
    rt.close()

    # memory after the second lap: the first sample taken once lap 2's frames were all tracked
    after_two = next((s for s in samples if s["t_s"] >= (lap_ends[min(1, len(lap_ends) - 1)] / FPS
                                                         if args.policy == "live" else 0.0)
                      and s["tracked"] >= (0 if args.policy == "live" else lap_ends[min(1, len(lap_ends) - 1)])),
                     final)
    growth = final["rss_mb_total"] / after_two["rss_mb_total"] - 1.0
    worst = max(lap_ate) / lap_ate[0] if lap_ate else float("nan")
    rows = [interval_rows(intervals, latency, i, baseline) for i in range(len(intervals))]
    print_intervals(rows[0], rows[-1], args.interval)
    worst_lap = min(laps_out, key=lambda r: r["tracked"] / r["played"]) if laps_out else None
    print(f"\nmemory (all processes): {after_two['rss_mb_total']:.0f} MB after lap 2 -> {final['rss_mb_total']:.0f} "
          f"MB at the end: {100 * growth:+.1f} % (target < 10 %)")
    print(f"ATE: first lap {lap_ate[0]:.2f} cm, worst lap {max(lap_ate):.2f} cm = {worst:.2f}x (target <= 1.2x)"
          if lap_ate else "ATE: no ground truth")
    if worst_lap is not None:
        print(f"frames tracked: worst lap {worst_lap['lap']}, {worst_lap['tracked']} of {worst_lap['played']} "
              f"({100 * worst_lap['tracked'] / worst_lap['played']:.1f} %, target >= 99 %)")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"data": str(args.data), "config": args.config, "sets": args.set, "frames": k,
                               "laps": len(lap_ends), "samples": samples, "lap_ate_cm": lap_ate,
                               "per_lap": laps_out, "intervals": rows,
                               "memory_growth_after_lap2": growth, "worst_lap_ate_ratio": worst}, indent=2))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
