"""Soak through the ROS node: a camera in the same space for an hour, at 30 Hz, through `slam_node` itself.

    python bench/ros_soak.py --data ../shared/data/7scenes_redkitchen_0_399 --kind 7scenes --minutes 60
    python bench/ros_soak.py --minutes 2        # the synthetic room (generated and cached), 320x240

The data set's frames are published from this process, forward then backward, again and again, with stamps that
keep increasing at 30 Hz: a bag played in a loop starts its stamps over at every pass, which the node takes for a
time jump and resets on. The node runs as its own process with its defaults (live policy and preset, the pipelined
runtime, the mesh process), as `bench/ros_replay.py` starts it. Latency is from the publication of a frame's images
here to the arrival here of the pose stamped with it.

Every `--interval` seconds of input (default 10 minutes) it prints the frames published, the poses received for
them, the latency (median, p90), the resident memory of each of the node's processes, their CPU time, page faults
and lost cores a frame, and the speed probe (bench/soak.py: a fixed piece of work every 5 s, the machine's own
speed); after each lap the ATE of its published poses. At the end, the first and the last interval side by side:
a latency that rises with a process's CPU a frame while the probe stays is the run's growth, one that rises with the
probe is the machine's. Targets (an hour live): poses for >= 99 % of the frames in every interval, the last
interval's median latency within 10 % of the first's. Writes JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ros_replay import TOPICS, process_tree_cpu, start_node, warmed_up  # noqa: E402
from soak import PROBE_EVERY, lap_order, memory_mb, process_counters, speed_probe_ms  # noqa: E402

from eslam_core.datasets import open_dataset  # noqa: E402
from eslam_core.evaluation.trajectory_error import ate  # noqa: E402
from eslam_core.trajectory import Trajectory  # noqa: E402
from eslam_ros.bag import CAMERA_FRAME  # noqa: E402

FPS = 30.0


class PoseListener:
    """Arrival times (monotonic, this process) and poses of the node's ~/pose by stamp, and its last status."""

    def __init__(self):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.node import Node

        from eslam_ros.conversions import msg_to_pose, stamp_to_sec

        self.node = Node("eslam_soak_bench")
        self.poses: dict[float, tuple[float, np.ndarray]] = {}
        self.status: dict[str, str] = {}
        self._stamp, self._pose = stamp_to_sec, msg_to_pose
        self.node.create_subscription(PoseStamped, "/slam_node/pose", self._on_pose, 1000)
        self.node.create_subscription(DiagnosticArray, "/slam_node/status", self._on_status, 10)

    def _on_pose(self, msg) -> None:
        self.poses[round(self._stamp(msg.header.stamp), 6)] = (time.monotonic(), self._pose(msg.pose))

    def _on_status(self, msg) -> None:
        self.status = {kv.key: kv.value for kv in msg.status[0].values}


class Camera:
    """The data set's frames as the messages a camera driver publishes, restamped at every publication."""

    def __init__(self, node, ds):
        from sensor_msgs.msg import CameraInfo, Image

        from eslam_ros.conversions import camera_info_from_intrinsics, depth_to_image, rgb_to_image, sec_to_stamp
        from eslam_ros.qos import player_qos

        self._stamp = sec_to_stamp
        zero = sec_to_stamp(0.0)
        frames = [ds[i] for i in range(len(ds))]
        self.rgb = [rgb_to_image(f.rgb, zero, CAMERA_FRAME) for f in frames]
        self.depth = [depth_to_image(f.depth, zero, CAMERA_FRAME) for f in frames]
        self.info = camera_info_from_intrinsics(ds.intrinsics, zero, CAMERA_FRAME)
        qos = player_qos("sensor_data", 10)
        self.publishers = (node.create_publisher(CameraInfo, TOPICS.camera_info, qos),
                           node.create_publisher(Image, TOPICS.rgb, qos), node.create_publisher(Image, TOPICS.depth, qos))

    def publish(self, i: int, seconds: float) -> None:
        stamp = self._stamp(seconds)
        for publisher, msg in zip(self.publishers, (self.info, self.rgb[i], self.depth[i])):
            msg.header.stamp = stamp
            publisher.publish(msg)

    def subscribed(self) -> bool:
        return all(p.get_subscription_count() > 0 for p in self.publishers)


def node_rss(root: int) -> dict[str, float]:
    """Resident memory (MB) by process name of the node and its descendants (its runtime's workers), and the
    anonymous part (the heap, without the shared map and frame ring a process has touched) as 'name anon'."""
    out: dict[str, float] = {}
    for pid, (name, _) in process_tree_cpu(root).items():
        memory = memory_mb(pid)
        out[name] = out.get(name, 0.0) + memory["rss"]
        out[f"{name} anon"] = out.get(f"{name} anon", 0.0) + memory["anon"]
    return out


def node_counters(root: int) -> dict[int, tuple[str, dict[str, float]]]:
    """process_counters (CPU seconds, page faults, context switches so far) and name of each of the node's
    processes, by pid."""
    return {pid: (name, process_counters(pid)) for pid, (name, _) in process_tree_cpu(root).items()}


def per_frame(before: dict, after: dict, frames: int) -> dict[str, dict[str, float]]:
    """node_counters' growth a frame between two readings, summed by process name (a process that started in
    between counts from zero; one that ended is not seen)."""
    out: dict[str, dict[str, float]] = {}
    for pid, (name, counters) in after.items():
        earlier = before.get(pid, (name, {}))[1]
        for key, value in counters.items():
            out.setdefault(name, {})[key] = out.get(name, {}).get(key, 0.0) + (value - earlier.get(key, 0.0)) / max(
                frames, 1)
    return out


def interval_row(number: int, stamps: list, published: dict, poses: dict, rss: dict, processes: dict,
                 probes: list) -> dict:
    latency = np.array([poses[s][0] - published[s] for s in stamps if s in poses])
    row = {"interval": number, "frames": len(stamps), "poses": len(latency),
            "pose_fraction": len(latency) / max(len(stamps), 1),
            "latency_ms_median": float(np.median(latency) * 1000) if len(latency) else float("nan"),
            "latency_ms_p90": float(np.percentile(latency, 90) * 1000) if len(latency) else float("nan"),
            "rss_mb": rss, "processes_per_frame": processes,
            "speed_probe_ms": float(np.median(probes)) if probes else float("nan")}
    print(f"interval {number}: poses for {row['poses']} of {row['frames']} frames ({100 * row['pose_fraction']:.1f} "
          f"%), latency median {row['latency_ms_median']:.1f} ms, p90 {row['latency_ms_p90']:.1f} ms, speed probe "
          f"{row['speed_probe_ms']:.2f} ms; CPU ms a frame "
          + ", ".join(f"{name} {1000 * c.get('cpu_s', float('nan')):.1f}" for name, c in processes.items())
          + "; RSS " + ", ".join(f"{name} {mb:.0f}" for name, mb in rss.items()) + " MB", flush=True)
    return row


def print_first_and_last(first: dict, last: dict) -> None:
    print(f"\nthe first and the last interval:  {'first':>8} {'last':>8}  last/first")
    for key, label in (("latency_ms_median", "latency, median (ms)"), ("latency_ms_p90", "latency, p90 (ms)"),
                       ("speed_probe_ms", "speed probe: fixed work, CPU ms (the machine)")):
        print(f"  {label:<52} {first[key]:8.2f} {last[key]:8.2f}  {last[key] / first[key]:6.2f}")
    early, late = first["processes_per_frame"], last["processes_per_frame"]
    for name in dict.fromkeys(list(early) + list(late)):  # (a worker is "python" until it names itself)
        for key, label, scale in (("cpu_s", "CPU ms a frame", 1000), ("minor_faults", "page faults a frame", 1),
                                  ("nonvoluntary", "cores taken away a frame", 1)):
            a = early.get(name, {}).get(key, float("nan")) * scale
            b = late.get(name, {}).get(key, float("nan")) * scale
            print(f"  {name + ': ' + label:<52} {a:8.2f} {b:8.2f}  {b / a if a > 0 else float('nan'):6.2f}")


def lap_row(number: int, stamps: list, poses: dict, truth: dict) -> dict:
    """The lap's ATE over its published poses (rigidly aligned)."""
    posed = [s for s in stamps if s in poses]
    known = [s for s in posed if truth[s] is not None]  # (ICL's first frame has no reference pose)
    ate_cm = float("nan")
    if len(known) >= 3:
        est = Trajectory(np.array(known), np.stack([poses[s][1] for s in known]))
        ate_cm = 100.0 * ate(est, Trajectory(est.timestamps, np.stack([truth[s] for s in known]))).rmse
    print(f"lap {number:3d}: ATE {ate_cm:.2f} cm, poses for {len(posed)} of {len(stamps)} frames", flush=True)
    return {"lap": number, "frames": len(stamps), "poses": len(posed), "ate_cm": ate_cm}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, help="data set folder (default: the synthetic room)")
    ap.add_argument("--kind", default="auto", help="data set kind (icl for ICL-NUIM)")
    ap.add_argument("--minutes", type=float, default=60.0, help="minutes of 30 Hz input")
    ap.add_argument("--interval", type=float, default=600.0, help="seconds of input per reported interval")
    ap.add_argument("--preset", default="live")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--policy", default="live")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="extra node parameter")
    ap.add_argument("--settle", type=float, default=20.0, help="seconds to wait for the last poses")
    ap.add_argument("--out", type=Path, default=Path("runs/ros_soak.json"))
    args = ap.parse_args()

    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    if args.data is None:
        from eslam_core.datasets.synthetic import ensure_scene
        from eslam_core.demo import default_cache

        args.data, args.kind = ensure_scene(default_cache(), n_frames=60, width=320, height=240), "tum"
    ds = open_dataset(args.data, args.kind)
    truth_of = ds.gt_poses()
    n, total = len(ds), int(args.minutes * 60 * FPS)
    work = Path(tempfile.mkdtemp(prefix="eslam_soak_"))
    node, log_path = start_node(args, work)
    listener = PoseListener()
    camera = Camera(listener.node, ds)
    executor = SingleThreadedExecutor()
    executor.add_node(listener.node)
    stop_spinning = threading.Event()

    def spin() -> None:
        while not stop_spinning.is_set():
            executor.spin_once(timeout_sec=0.1)

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    published: dict[float, float] = {}  # stamp -> when its images were published
    truth: dict[float, np.ndarray] = {}
    laps: list[list[float]] = [[]]
    intervals: list[list[float]] = [[]]
    rows, lap_rows = [], []
    probes: list[float] = []  # the speed probe's figures since the last interval was reported
    counted = (0, {})  # frames played and node_counters when the last interval was reported

    def report_interval(stamps: list) -> None:
        """An interval, reported a second after its last frame (when its poses are in); the processes' counters and
        the probes are those since the previous report."""
        nonlocal counted
        now = (len(published), node_counters(node.pid))
        rows.append(interval_row(len(rows) + 1, stamps, published, listener.poses, node_rss(node.pid),
                                 per_frame(counted[1], now[1], now[0] - counted[0]), probes[:]))
        counted = now
        probes.clear()
    print(f"{n} frames, {args.minutes:.0f} minutes at 30 Hz through slam_node (preset {args.preset}, {args.policy} "
          f"policy); node log {log_path}", flush=True)
    try:
        deadline = time.monotonic() + 600
        while not camera.subscribed() and time.monotonic() < deadline and node.poll() is None:
            time.sleep(0.1)
        played_at = -1e9
        while not warmed_up(listener.status) and time.monotonic() < deadline and node.poll() is None:
            if not listener.poses and time.monotonic() - played_at > 5.0:  # the first frame alone: the warm-up
                camera.publish(0, 0.0)
                played_at = time.monotonic()
            time.sleep(0.1)
        print("map warmed up; streaming ...", flush=True)
        order = (i for lap in range(total // n + 2) for i in lap_order(n, lap))
        next(order)  # the warm-up's frame
        start = time.monotonic()
        counted = (0, node_counters(node.pid))
        for k in range(1, total):
            if node.poll() is not None:
                break
            i = next(order)
            time.sleep(max(0.0, start + (k - 1) / FPS - time.monotonic()))
            stamp = round(k / FPS, 6)
            published[stamp] = time.monotonic()
            camera.publish(i, stamp)
            truth[stamp] = truth_of[i]
            laps[-1].append(stamp)
            intervals[-1].append(stamp)
            if k % PROBE_EVERY == 0:
                probes.append(speed_probe_ms())
            if (k + 1) % n == 0:
                laps.append([])
            if (k + 1) % int(args.interval * FPS) == 0:
                intervals.append([])
            if len(laps[-1]) == int(FPS) and len(laps) >= 2:  # a second into a lap: the one before is all posed
                lap_rows.append(lap_row(len(lap_rows) + 1, laps[-2], listener.poses, truth))
                laps[-2] = []
            if len(intervals[-1]) == int(FPS) and len(intervals) >= 2:
                report_interval(intervals[-2])
        end_of_play = time.monotonic()
        while time.monotonic() - end_of_play < args.settle and len(listener.poses) < len(published):
            time.sleep(1.0)
        for stamps in laps[len(lap_rows):]:  # those not reported yet (the last, or the last two)
            if stamps:
                lap_rows.append(lap_row(len(lap_rows) + 1, stamps, listener.poses, truth))
        for stamps in intervals[len(rows):]:
            if stamps:
                report_interval(stamps)
        status = dict(listener.status)
    finally:
        if node.poll() is None:
            node.send_signal(signal.SIGINT)
            try:
                node.wait(120)
            except subprocess.TimeoutExpired:
                os.killpg(node.pid, signal.SIGKILL)
        stop_spinning.set()  # (before the executor goes: see bench/ros_replay.py)
        spinner.join()
        executor.shutdown()
        listener.node.destroy_node()
        rclpy.try_shutdown()

    if rows:
        first, last = rows[0], rows[-1]
        worst = min(rows, key=lambda r: r["pose_fraction"])
        print(f"\nposes: worst interval {worst['interval']}: {100 * worst['pose_fraction']:.1f} % of its frames "
              f"(target >= 99 %)")
        print(f"latency median: first interval {first['latency_ms_median']:.1f} ms, last "
              f"{last['latency_ms_median']:.1f} ms: {last['latency_ms_median'] / first['latency_ms_median']:.2f}x "
              f"(target <= 1.1x)")
        print_first_and_last(first, last)
        print("memory (MB), first -> last interval: " + ", ".join(
            f"{name} {first['rss_mb'].get(name, float('nan')):.0f} -> {mb:.0f}" for name, mb in last["rss_mb"].items()))
    finite = [r["ate_cm"] for r in lap_rows if np.isfinite(r["ate_cm"])]
    if finite:
        print(f"ATE: first lap {finite[0]:.2f} cm, worst lap {max(finite):.2f} cm = {max(finite) / finite[0]:.2f}x")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"data": str(args.data), "minutes": args.minutes, "preset": args.preset,
                                    "policy": args.policy, "params": args.param, "frames": len(published),
                                    "node_exit_code": node.returncode, "intervals": rows, "laps": lap_rows,
                                    "node_status": status, "node_log": str(log_path)}, indent=2))
    print(f"node exit code {node.returncode}; results -> {args.out}")
    return 0 if node.returncode == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
