"""Live replay through the ROS node: latency from image to published pose, pose rate, frames dropped.

    python bench/ros_replay.py --data ../shared/data/icl_office_kt0 --kind icl [--frames 0:300] [--rate 1]
    python bench/ros_replay.py                  # the synthetic room (generated and cached), 320x240

Writes the data set as a bag (30 Hz), starts `slam_node` as its own process (its default live policy and preset
unless told otherwise; own ROS domain, discovery limited to this machine), plays the bag at the recorded pace and
listens to the node. Latency is measured in this process: from the arrival of an RGB image here to the arrival of
the pose stamped with that image's stamp (both on the same clock; the node receives the image at about the same
time as this listener). Frames dropped are the synchronized pairs that never got a pose (the live policy skips to
the newest frame when tracking falls behind). Prints a table and writes JSON.
"""
from __future__ import annotations

import argparse
import ast
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

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from eslam_core.cli import parse_frames  # noqa: E402
from eslam_core.datasets import open_dataset  # noqa: E402
from eslam_core.datasets.tum import write_tum  # noqa: E402
from eslam_core.evaluation.trajectory_error import ate  # noqa: E402
from eslam_core.trajectory import Trajectory  # noqa: E402
from eslam_ros.bag import BagTopics, bag_timestamps, play_bag, write_bag  # noqa: E402
from eslam_ros.qos import use_shipped_fastdds_profile  # noqa: E402

TOPICS = BagTopics()


def node_command(args, out_dir: Path) -> list[str]:
    params = {"preset": args.preset, "workers": args.workers, "policy": args.policy, "output_dir": str(out_dir)}
    params.update(dict(s.split("=", 1) for s in args.param))
    command = [sys.executable, "-m", "eslam_ros.slam_node", "--ros-args"]
    for name, value in params.items():
        command += ["-p", f"{name}:={value}"]
    for name, topic in (("rgb/image", TOPICS.rgb), ("depth/image", TOPICS.depth),
                        ("rgb/camera_info", TOPICS.camera_info)):
        command += ["-r", f"{name}:={topic}"]
    return command


def start_node(args, work: Path) -> tuple[subprocess.Popen, Path]:
    """`slam_node` as its own process in a ROS domain of its own (discovery on this machine only), and rclpy
    initialised in this process on that domain; the node's log goes to work/node.log."""
    import rclpy

    domain = 1 + os.getpid() % 101
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    os.environ.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    use_shipped_fastdds_profile()  # as `eslam bag play` does: large images over shared memory
    log_path = work / "node.log"
    node = subprocess.Popen(node_command(args, work / "node_out"), env=env, cwd=REPO, stdout=open(log_path, "w"),
                            stderr=subprocess.STDOUT, start_new_session=True)
    rclpy.init(domain_id=domain)
    return node, log_path


class Listener:
    """Arrival times (monotonic, this process) of images and poses by stamp, and the node's last status."""

    def __init__(self):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Odometry
        from rclpy.node import Node
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import Image

        from eslam_ros.conversions import msg_to_pose, stamp_to_sec

        self.node = Node("eslam_replay_bench")
        self.images: dict[float, float] = {}
        self.poses: dict[float, tuple[float, np.ndarray]] = {}
        self.sigmas: dict[float, float] = {}  # ~/odom's largest position sigma (m) by stamp
        self.status: dict[str, str] = {}
        self._stamp, self._pose = stamp_to_sec, msg_to_pose
        self.node.create_subscription(Image, TOPICS.rgb, self._on_image, qos_profile_sensor_data)
        self.node.create_subscription(PoseStamped, "/slam_node/pose", self._on_pose, 1000)
        self.node.create_subscription(Odometry, "/slam_node/odom", self._on_odom, 1000)
        self.node.create_subscription(DiagnosticArray, "/slam_node/status", self._on_status, 10)

    def _on_image(self, msg) -> None:
        self.images.setdefault(round(self._stamp(msg.header.stamp), 6), time.monotonic())

    def _on_pose(self, msg) -> None:
        self.poses[round(self._stamp(msg.header.stamp), 6)] = (time.monotonic(), self._pose(msg.pose))

    def _on_odom(self, msg) -> None:
        position = np.reshape(msg.pose.covariance, (6, 6))[:3, :3]
        self.sigmas[round(self._stamp(msg.header.stamp), 6)] = float(np.sqrt(np.linalg.eigvalsh(position)[-1]))

    def _on_status(self, msg) -> None:
        self.status = {kv.key: kv.value for kv in msg.status[0].values}


def warmed_up(status: dict) -> bool:
    return int(status.get("map_version", 0)) > 0 and int(status.get("keyframe_queue_depth", 1)) == 0


def process_tree_cpu(root: int) -> dict[int, tuple[str, float]]:
    """Name and CPU seconds (user + system) of `root` and each of its descendants, by pid (names from
    /proc/<pid>/stat: the runtime's workers name themselves eslam-tracker, eslam-mapper, eslam-mesh; the root is
    "node"); Linux only, else empty."""
    stats = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                text = (entry / "stat").read_text()
            except OSError:
                continue
            name, rest = text[text.index("(") + 1:text.rindex(")")], text[text.rindex(")") + 2:].split()
            stats[int(entry.name)] = (name, int(rest[1]), (int(rest[11]) + int(rest[12])) / os.sysconf("SC_CLK_TCK"))
    tree, frontier = {root}, [root]
    while frontier:
        parent = frontier.pop()
        children = [pid for pid, (_, ppid, _) in stats.items() if ppid == parent and pid not in tree]
        tree.update(children)
        frontier += children
    return {pid: ("node" if pid == root else stats[pid][0], stats[pid][2]) for pid in tree & set(stats)}


def cpu_shares(before: dict[int, tuple[str, float]], after: dict[int, tuple[str, float]],
               seconds: float) -> dict[str, float]:
    """% of one core by process name between two `process_tree_cpu` readings, per pid (a process that started in
    between counts from zero; one that ended is not seen, and a pid reused under another name starts again)."""
    shares: dict[str, float] = {}
    for pid, (name, cpu) in after.items():
        old_name, old_cpu = before.get(pid, (name, 0.0))
        used = cpu - old_cpu if old_name == name else cpu
        shares[name] = shares.get(name, 0.0) + 100 * used / seconds
    return shares


def print_profile(status: dict) -> None:
    """The per-stage profile from the node's last status: the node's own share, then the workers' stages."""
    if not status:
        return
    print("per-stage profile (ms per event):")
    for key, per in (("node_ms_per_pair_in", "rgb-depth pair"), ("node_ms_per_pose_out", "published pose")):
        if key in status:
            print(f"  {'node: ' + key[8:]:<52} {float(status[key]):7.1f}  per {per}")
    try:
        stages = ast.literal_eval(status.get("stage_ms", "{}"))
    except (ValueError, SyntaxError):
        stages = {}
    for stage, ms in stages.items():
        print(f"  {stage:<52} {ms:7.1f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, help="data set folder (default: the synthetic room)")
    ap.add_argument("--kind", default="auto", help="data set kind (icl for ICL-NUIM)")
    ap.add_argument("--frames", type=parse_frames, default=(0, None), help="A:B, frames to write (default all)")
    ap.add_argument("--rate", type=float, default=1.0, help="playback rate (1 = recorded 30 Hz)")
    ap.add_argument("--preset", default="live", help="the node's preset (default: its default)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--policy", default="live")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                    help="extra node parameter, e.g. eslam.tracking.iterations=6")
    ap.add_argument("--settle", type=float, default=20.0, help="seconds to wait for the last poses after playback")
    ap.add_argument("--out", type=Path, default=Path("bench_ros_replay.json"))
    ap.add_argument("--trajectory", type=Path, help="also write the published poses here (TUM; for evo or a per-frame "
                                                    "comparison with an offline run)")
    args = ap.parse_args()

    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    if args.data is None:
        from eslam_core.demo import default_cache
        from eslam_core.datasets.synthetic import ensure_scene

        args.data, args.kind = ensure_scene(default_cache(), n_frames=60, width=320, height=240), "tum"
    ds = open_dataset(args.data, args.kind)
    ds = ds.subset(args.frames[0], args.frames[1] if args.frames[1] is not None else len(ds))
    work = Path(tempfile.mkdtemp(prefix="eslam_replay_"))
    print(f"writing {len(ds)} frames of {args.data} as a bag ...", flush=True)
    lead_in = write_bag(ds.subset(0, 1), work / "lead_in.mcap", fps=30.0).path
    bag = write_bag(ds.subset(1, len(ds)), work / "replay.mcap", fps=30.0).path

    node, log_path = start_node(args, work)
    listener = Listener()
    executor = SingleThreadedExecutor()
    executor.add_node(listener.node)
    stop_spinning = threading.Event()

    def spin() -> None:
        while not stop_spinning.is_set():
            executor.spin_once(timeout_sec=0.1)

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    try:
        qos = "sensor_data" if args.policy == "live" else "reliable"
        # The first frame alone, then the stream once the map's warm-up on it is done (the node's status shows a
        # map and no keyframe waiting): as a camera that keeps streaming would see it, without the warm-up
        # swallowing a short sequence.
        start, deadline = time.monotonic(), time.monotonic() + 600
        played_at = -1e9
        while not warmed_up(listener.status) and time.monotonic() < deadline and node.poll() is None:
            if not listener.poses and time.monotonic() - played_at > 5.0:  # best effort: it may have been lost
                play_bag(lead_in, wait_for_subscribers=60.0, qos=qos)
                played_at = time.monotonic()
            time.sleep(0.1)
        warm_up_s = time.monotonic() - start
        load_before = os.getloadavg()
        print(f"map warmed up in {time.monotonic() - start:.1f} s; streaming {len(ds) - 1} frames ...", flush=True)
        cpu_before, bench_before, play_start = process_tree_cpu(node.pid), time.process_time(), time.monotonic()
        played = play_bag(bag, rate=args.rate, wait_for_subscribers=60.0, qos=qos)
        end_of_play = time.monotonic()
        cpu_after, bench_after = process_tree_cpu(node.pid), time.process_time()
        cpu_share = cpu_shares(cpu_before, cpu_after, end_of_play - play_start)
        cpu_share["this benchmark (player, listener)"] = 100 * (bench_after - bench_before) / (end_of_play - play_start)
        last = len(listener.poses)
        while time.monotonic() - end_of_play < args.settle:  # the node may still be tracking queued frames
            time.sleep(1.0)
            if len(listener.poses) == last and time.monotonic() - end_of_play > 3.0:
                break
            last = len(listener.poses)
        status = dict(listener.status)
    finally:
        if node.poll() is None:
            node.send_signal(signal.SIGINT)
            try:
                node.wait(120)
            except subprocess.TimeoutExpired:
                os.killpg(node.pid, signal.SIGKILL)
        # The spinning thread ends before the executor and the context go: left spinning, it made this process
        # abort (SIGABRT) at exit in about one run of ten, after its results were written.
        stop_spinning.set()
        spinner.join()
        executor.shutdown()
        listener.node.destroy_node()
        rclpy.try_shutdown()

    stamps = sorted(listener.poses)
    bag_stamps = np.round(bag_timestamps(ds, 30.0), 6)
    stream = {s: v for s, v in listener.poses.items() if s != bag_stamps[0]}  # the lead-in's pose is the warm-up's
    pose_times = sorted(t for t, _ in stream.values())
    latency = np.array([t - listener.images[s] for s, (t, _) in stream.items() if s in listener.images])
    truth = ds.gt_poses()
    known = [(s, truth[i]) for i, s in enumerate(bag_stamps) if truth[i] is not None and s in listener.poses]
    ate_cm = None
    if args.trajectory is not None and stamps:
        args.trajectory.parent.mkdir(parents=True, exist_ok=True)
        write_tum(args.trajectory, Trajectory(np.array(stamps), np.stack([listener.poses[s][1] for s in stamps])))
    flagged = None
    if len(known) >= 3:
        est = Trajectory(np.array([s for s, _ in known]), np.stack([listener.poses[s][1] for s, _ in known]))
        ref = Trajectory(est.timestamps, np.stack([p for _, p in known]))
        result = ate(est, ref)
        ate_cm = 100 * result.rmse
        # Published poses off by more than 2 cm (after the ATE alignment) and how many of them said so: ~/odom's
        # covariance wider than quality.degraded_sigma_m (a degraded pose) or unknown (lost).
        off = result.errors > 0.02
        sigma = np.array([listener.sigmas.get(s, np.inf) for s in est.timestamps])
        flagged = {"published_over_2cm": int(off.sum()), "of_which_flagged": int((off & (sigma > 0.02)).sum()),
                   "worst_unflagged_cm": float(100 * result.errors[off & ~(sigma > 0.02)].max())
                   if (off & ~(sigma > 0.02)).any() else None}
    results = {
        "data": str(Path(args.data).resolve()), "frames": len(ds), "rate": args.rate, "preset": args.preset,
        "workers": args.workers, "policy": args.policy, "params": args.param, "node_exit_code": node.returncode,
        "messages_played": played.messages, "play_seconds": played.seconds,
        "images_seen_here": len(listener.images), "poses": len(stamps),
        "pose_rate_hz": (len(pose_times) - 1) / (pose_times[-1] - pose_times[0]) if len(pose_times) > 2 else 0.0,
        "warm_up_s": warm_up_s,
        "frames_without_pose": len(ds) - len(stamps),  # the lead-in frame has one
        "latency_s_by_stamp": {s: t - listener.images[s] for s, (t, _) in stream.items() if s in listener.images},
        "latency_ms": {"median": float(np.median(latency) * 1000), "p90": float(np.percentile(latency, 90) * 1000),
                       "p99": float(np.percentile(latency, 99) * 1000),
                       "max": float(latency.max() * 1000), "mean": float(latency.mean() * 1000)}
        if len(latency) else None,
        "ate_rmse_cm_of_published_poses": ate_cm, "poses_over_2cm": flagged, "cpu_percent_during_play": cpu_share, "node_status": status, "load_before": load_before,
        "node_log": str(log_path),
    }
    print(f"\n{len(ds)} frames at {30 * args.rate:.0f} Hz through slam_node (preset {args.preset}, "
          f"{args.workers} worker(s), {args.policy} policy); load before {load_before[0]:.2f}")
    print(f"map warm-up on the first frame: {warm_up_s:.1f} s; then the stream")
    print(f"poses published: {len(stamps)} ({results['pose_rate_hz']:.2f} Hz over the stream), frames without a pose: "
          f"{results['frames_without_pose']} (runtime dropped: {status.get('frames_dropped', '?')})")
    if results["latency_ms"]:
        lat = results["latency_ms"]
        print(f"latency image -> pose: median {lat['median']:.0f} ms, p90 {lat['p90']:.0f} ms, p99 {lat['p99']:.0f} ms, "
              f"max {lat['max']:.0f} ms")
    if ate_cm is not None:
        print(f"ATE RMSE of the published (as-tracked) poses: {ate_cm:.2f} cm over {len(known)} poses")
        print(f"published poses over 2 cm off: {flagged['published_over_2cm']}, of which ~/odom said so (sigma over "
              f"2 cm or lost): {flagged['of_which_flagged']}")
    print("CPU during the stream (% of one core): " + ", ".join(f"{name} {share:.0f}"
                                                               for name, share in cpu_share.items()))
    print_profile(status)
    print(f"node exit code {node.returncode}; log {log_path}")
    args.out.write_text(json.dumps(results, indent=2))
    print(f"results -> {args.out}")
    return 0 if node.returncode == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
