"""rosbag2 tools, with the pure-Python `rosbags` library (no rosbag2 installation needed).

    eslam bag write DATASET OUT.mcap   a data set eslam_core reads -> a rosbag2 bag (MCAP or sqlite3)
    eslam bag play BAG [--rate R] [--loop]   publish a bag's messages on their topics at the recorded pace
    eslam bag run BAG --config PRESET --out DIR   a bag through the node's input pipeline into SLAM, without DDS

Bags written here hold, per frame (header stamp = the frame's time stamp, bag time = the same):
    /camera/color/image_raw      sensor_msgs/Image rgb8
    /camera/depth/image_raw      sensor_msgs/Image 16UC1 (millimetres, REP 118; 0 = no measurement), registered
                                 to the colour image
    /camera/color/camera_info    sensor_msgs/CameraInfo (pinhole, no distortion)
    /ground_truth/pose           geometry_msgs/PoseStamped, camera-to-world in OpenCV axes, frame "world"
                                 (frames without ground truth have none)
    /odom                        with --odometry: nav_msgs/Odometry odom -> base_link made from the ground truth
                                 and a base -> camera extrinsic (an exact wheel odometry; odom = world)
Images carry the frame_id `camera_color_optical_frame`. Data sets whose time stamps are frame numbers (ICL-NUIM,
Replica) are timed at `fps` frames per second (stamp = number / fps), so a 30 Hz sequence plays at 30 Hz.

A rosbag2 bag is a folder (metadata.yaml + a storage file). `OUT.mcap` or `OUT.db3` names the folder `OUT` and
picks the storage; a folder name without suffix gets MCAP. Commands reading a bag accept the folder or `OUT.mcap`.
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import logging
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Optional, Sequence

import numpy as np
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.errors import ReaderError, WriterError
from rosbags.typesys import Stores, get_typestore
from tqdm import tqdm

from eslam_core.cli import parse_frames, parse_overrides
from eslam_core.config import Config, list_presets, load_config, save_config
from eslam_core.datasets import RGBDDataset, open_dataset
from eslam_core.datasets.tum import write_tum
from eslam_core.evaluation.trajectory_error import ate
from eslam_core.trajectory import Trajectory
from eslam_ros.conversions import (
    camera_info_from_intrinsics,
    depth_to_image,
    msg_to_pose,
    pose_to_msg,
    rgb_to_image,
    sec_to_stamp,
    stamp_to_sec,
)

log = logging.getLogger("eslam")

CAMERA_FRAME = "camera_color_optical_frame"
GROUND_TRUTH_FRAME = "world"
# Data set kinds whose time stamps are frame numbers, not seconds.
FRAME_NUMBER_KINDS = ("icl", "replica")
STORAGE_SUFFIXES = {".mcap": "mcap", ".db3": "sqlite3"}
STORAGE_PLUGINS = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
IMAGE_TYPE, INFO_TYPE = "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
# base_link -> camera optical frame of a camera 10 cm ahead of and 30 cm above the base, looking forward (x, y, z,
# qx, qy, qz, qw): optical z = base x, optical x = -base y, optical y = -base z.
FORWARD_CAMERA = (0.1, 0.0, 0.3, -0.5, 0.5, -0.5, 0.5)
_TYPESTORE = get_typestore(Stores.ROS2_JAZZY)  # type hashes match rclpy's Jazzy messages


class BagError(ValueError):
    """A bag cannot be written, read or played; the message names the file or topic at fault and the fix."""


@dataclass(frozen=True)
class BagTopics:
    """Topic names of a bag's camera streams and ground truth."""

    rgb: str = "/camera/color/image_raw"
    depth: str = "/camera/depth/image_raw"
    camera_info: str = "/camera/color/camera_info"
    ground_truth: str = "/ground_truth/pose"
    odometry: str = "/odom"


@dataclass(frozen=True)
class BagOdometry:
    """An odometry stream in a bag: nav_msgs/Odometry odom_frame -> base_frame, and where the camera sits on the
    base ([x, y, z, qx, qy, qz, qw] of the camera optical frame in base_frame)."""

    odom_frame: str = "odom"
    base_frame: str = "base_link"
    base_to_camera: tuple = FORWARD_CAMERA

    def base_camera(self) -> np.ndarray:
        from eslam_ros.tf_chain import pose_from_xyz_quaternion

        return pose_from_xyz_quaternion(self.base_to_camera)


# ================================================================================================= paths


def bag_folder(out: Path | str, storage: Optional[str] = None) -> tuple[Path, str]:
    """(bag folder, storage) for an output name: 'x.mcap' -> ('x', 'mcap'), 'x.db3' -> ('x', 'sqlite3')."""
    out = Path(out)
    implied = STORAGE_SUFFIXES.get(out.suffix)
    if storage is None:
        storage = implied or "mcap"
    if storage not in STORAGE_PLUGINS:
        raise BagError(f"unknown bag storage '{storage}': choose one of {', '.join(STORAGE_PLUGINS)}")
    if implied is not None and implied != storage:
        raise BagError(f"{out} has the suffix of {implied} storage but --storage {storage} was asked for; "
                       f"drop the suffix or the option")
    return (out.with_suffix("") if implied else out), storage


def resolve_bag(path: Path | str) -> Path:
    """The bag to read: a rosbag2 folder or storage file, or 'x.mcap' standing for the folder 'x' written here."""
    path = Path(path)
    if path.exists():
        return path
    folder = path.with_suffix("")
    if path.suffix in STORAGE_SUFFIXES and folder.is_dir():
        return folder
    raise BagError(f"bag not found: {path} (give the bag folder that `eslam bag write` created, or its .mcap / "
                   f".db3 file)")


def _open_reader(path: Path | str) -> Reader:
    bag = resolve_bag(path)
    try:
        reader = Reader(bag)
        reader.open()
    except (ReaderError, FileNotFoundError) as error:
        raise BagError(f"{bag} is not a readable rosbag2 bag: {error}") from None
    return reader


# ================================================================================================= write


@dataclass(frozen=True)
class BagWriteSummary:
    path: Path
    storage: str
    frames: int
    ground_truth_poses: int
    duration_s: float
    topics: BagTopics


def bag_timestamps(dataset: RGBDDataset, fps: float) -> np.ndarray:
    """Seconds of each frame: the data set's time stamps, or frame number / fps where those are frame numbers."""
    stamps = dataset.timestamps()
    if dataset.kind in FRAME_NUMBER_KINDS:
        if not fps > 0:
            raise BagError(f"fps must be positive to time the frames of a {dataset.kind} sequence, got {fps}")
        stamps = stamps / fps
    if np.any(stamps < 0) or np.any(np.diff(stamps) <= 0):
        raise BagError(f"{dataset.root}: time stamps must be >= 0 and strictly increasing to be written as a bag")
    return stamps


def write_bag(
    dataset: RGBDDataset,
    out: Path | str,
    *,
    storage: Optional[str] = None,
    fps: float = 30.0,
    depth_encoding: str = "16UC1",
    topics: BagTopics = BagTopics(),
    progress: bool = False,
    odometry: Optional[BagOdometry] = None,
) -> BagWriteSummary:
    """Write `dataset` as a rosbag2 bag (see the module docstring for its topics) and return what was written.

    `odometry`: also write the ground truth as the exact odometry of a base carrying the camera (topics.odometry),
    before the images of each frame (an odometry sample at every image stamp)."""
    folder, storage = bag_folder(out, storage)
    stamps = bag_timestamps(dataset, fps)
    gt_poses = dataset.gt_poses()
    intrinsics = dataset.intrinsics
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry
    from rclpy.serialization import serialize_message  # rclpy: the same CDR bytes a live publisher sends

    try:
        writer = Writer(folder, version=9, storage_plugin=STORAGE_PLUGINS[storage])
        writer.open()
    except WriterError as error:
        raise BagError(f"cannot create the bag {folder}: {error} (delete it or choose another name)") from None
    written_gt = 0
    try:
        rgb_c = writer.add_connection(topics.rgb, IMAGE_TYPE, typestore=_TYPESTORE)
        depth_c = writer.add_connection(topics.depth, IMAGE_TYPE, typestore=_TYPESTORE)
        info_c = writer.add_connection(topics.camera_info, INFO_TYPE, typestore=_TYPESTORE)
        gt_c = writer.add_connection(topics.ground_truth, POSE_TYPE, typestore=_TYPESTORE) if any(
            p is not None for p in gt_poses) else None
        odom_c = writer.add_connection(topics.odometry, ODOMETRY_TYPE, typestore=_TYPESTORE) if (
            odometry is not None and gt_c is not None) else None
        camera_base = np.linalg.inv(odometry.base_camera()) if odom_c is not None else None
        for i in tqdm(range(len(dataset)), desc="bag", unit="frame", disable=not progress):
            frame = dataset[i]
            stamp = sec_to_stamp(stamps[i])
            log_time = stamp.sec * 1_000_000_000 + stamp.nanosec
            if odom_c is not None and gt_poses[i] is not None:
                odom = Odometry(child_frame_id=odometry.base_frame)
                odom.header.stamp, odom.header.frame_id = stamp, odometry.odom_frame
                odom.pose.pose = pose_to_msg(gt_poses[i] @ camera_base)  # T_odom_base = T_odom_cam @ T_cam_base
                writer.write(odom_c, log_time, serialize_message(odom))
            writer.write(rgb_c, log_time, serialize_message(rgb_to_image(frame.rgb, stamp, CAMERA_FRAME)))
            writer.write(depth_c, log_time, serialize_message(
                depth_to_image(frame.depth, stamp, CAMERA_FRAME, depth_encoding)))
            writer.write(info_c, log_time, serialize_message(camera_info_from_intrinsics(intrinsics, stamp,
                                                                                         CAMERA_FRAME)))
            if gt_c is not None and gt_poses[i] is not None:
                gt = PoseStamped(pose=pose_to_msg(gt_poses[i]))
                gt.header.stamp, gt.header.frame_id = stamp, GROUND_TRUTH_FRAME
                writer.write(gt_c, log_time, serialize_message(gt))
                written_gt += 1
        writer.close()
    except BaseException:
        writer.abort()  # no half-written bag left behind
        raise
    return BagWriteSummary(folder, storage, len(dataset), written_gt, float(stamps[-1] - stamps[0]), topics)


# ================================================================================================= play


@dataclass(frozen=True)
class PlaySummary:
    messages: int
    loops: int
    seconds: float
    subscribers_found: bool


def message_class(msgtype: str) -> type:
    """rclpy class of a message type name such as 'sensor_msgs/msg/Image'."""
    package, _, name = msgtype.rpartition("/")
    module_name = package.replace("/", ".")
    try:
        return getattr(importlib.import_module(module_name), name)
    except (ImportError, AttributeError):
        raise BagError(f"message type {msgtype} is not installed for rclpy: install its package (e.g. "
                       f"pip install ros-jazzy-common-interfaces) or leave its topic out with --topics") from None


def play_offset(log_time_ns: int, first_ns: int, rate: float) -> float:
    """Seconds after the first message at which a message is due: recorded pace divided by `rate` (0: at once)."""
    return 0.0 if rate == 0 else (log_time_ns - first_ns) / 1e9 / rate


def play_bag(
    path: Path | str,
    *,
    rate: float = 1.0,
    passes: int = 1,
    wait_for_subscribers: float = 10.0,
    topics: Optional[Sequence[str]] = None,
    qos: str = "reliable",
    queue_depth: int = 100,
    wait_ready: Optional[str] = None,
) -> PlaySummary:
    """Publish the bag's messages (raw CDR bytes) on their topics at the recorded pace times `rate`.

    rate 0 publishes as fast as the subscribers acknowledge (reliable QoS: each message waits until every reliable
    subscription has it). Before starting, waits up to `wait_for_subscribers` seconds until every image and
    camera-info topic has a subscriber. `passes`: how many times the bag is played (0 = until interrupted); each
    pass starts over with the bag's own stamps. rclpy is initialised here (and shut down again) unless the caller
    did it. `wait_ready`: the SLAM node's name (e.g. /slam_node): after the subscribers, also wait (same timeout)
    until its ~/status reports `ready` (it sees this player on every input and takes frames without loss).
    """
    import rclpy
    from rclpy.duration import Duration
    from rclpy.node import Node

    from eslam_ros.qos import player_qos

    if not (rate >= 0 and math.isfinite(rate)):
        raise BagError(f"--rate must be >= 0 (1 = recorded pace, 0 = as fast as acknowledged), got {rate}")
    if passes < 0:
        raise BagError(f"passes must be >= 0 (0 = loop until interrupted), got {passes}")
    reader = _open_reader(path)
    connections = [c for c in reader.connections if topics is None or c.topic in topics]
    if topics is not None:
        missing = sorted(set(topics) - {c.topic for c in connections})
        if missing:
            raise BagError(f"topic(s) {', '.join(missing)} not in {path}; its topics: "
                           f"{', '.join(sorted({c.topic for c in reader.connections}))}")
    owns_rclpy = not rclpy.ok()
    if owns_rclpy:
        rclpy.init()
    node = Node("eslam_bag_player")
    try:
        profile = player_qos(qos, queue_depth)
        publishers = {}
        for c in connections:
            if c.topic not in publishers:
                publishers[c.topic] = node.create_publisher(message_class(c.msgtype), c.topic, profile)
        sensors = [publishers[c.topic] for c in connections if c.msgtype in (IMAGE_TYPE, INFO_TYPE)]
        found = _wait_for_subscribers(sensors, wait_for_subscribers)
        # A node in REP 105 mode also takes the odometry; one that does not never subscribes, so its wait is short.
        odometry = [publishers[c.topic] for c in connections if c.msgtype == ODOMETRY_TYPE]
        if odometry and not _wait_for_subscribers(odometry, min(ODOMETRY_SUBSCRIBER_WAIT_S, wait_for_subscribers)):
            log.info("no subscriber on %s: playing it anyway", ", ".join(p.topic_name for p in odometry))
        if not found:
            log.warning("no subscriber on %s after %.0f s: playing anyway",
                        ", ".join(p.topic_name for p in sensors if p.get_subscription_count() == 0),
                        wait_for_subscribers)
        if wait_ready and not wait_until_ready(node, wait_ready, wait_for_subscribers):
            log.warning("%s did not report ready within %.0f s: playing anyway", wait_ready, wait_for_subscribers)
        count, loops, start = 0, 0, time.monotonic()
        while True:
            first: Optional[int] = None
            for c, t, raw in reader.messages(connections=connections):  # streamed: bags can be large
                if first is None:
                    first, pass_start = t, time.monotonic()
                delay = pass_start + play_offset(t, first, rate) - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                publisher = publishers[c.topic]
                publisher.publish(raw)
                if rate == 0:
                    publisher.wait_for_all_acked(Duration(seconds=5.0))
                count += 1
            loops += 1
            if loops == passes:
                break
        for publisher in publishers.values():  # let reliable subscribers receive everything before we go
            publisher.wait_for_all_acked(Duration(seconds=5.0))
        return PlaySummary(count, loops, time.monotonic() - start, found)
    finally:
        reader.close()
        node.destroy_node()
        if owns_rclpy:
            rclpy.try_shutdown()


ODOMETRY_SUBSCRIBER_WAIT_S = 2.0


def _wait_for_subscribers(publishers: Sequence[Any], timeout: float) -> bool:
    """Wait until every publisher has a subscriber; True if they all do before `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while any(p.get_subscription_count() == 0 for p in publishers):
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.05)
    # Matching is seen by the publisher first; give the subscriber side a moment to match us too, or it would
    # discard the first messages.
    time.sleep(0.5)
    return True


def wait_until_ready(node: Any, slam_node: str, timeout: float) -> bool:
    """Spin `node` until the ~/status of `slam_node` says ready=True; False after `timeout` seconds."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray

    from eslam_ros.qos import output_qos

    ready = []

    def on_status(msg: Any) -> None:
        values = {kv.key: kv.value for status in msg.status for kv in status.values}
        if values.get("ready") == "True":
            ready.append(True)

    topic = slam_node.rstrip("/") + "/status"
    subscription = node.create_subscription(DiagnosticArray, topic, on_status, output_qos())
    deadline = time.monotonic() + timeout
    try:
        while not ready and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
    finally:
        node.destroy_subscription(subscription)
    return bool(ready)


# ================================================================================================= run


@dataclass
class BagRunSummary:
    out_dir: Path
    frames: int
    seconds: float
    seconds_per_frame: float
    ate_rmse_cm: Optional[float]
    skipped: dict
    unpaired: dict
    mesh_path: Optional[Path]


def _find_connection(reader: Reader, topic: str, msgtype: str, option: str, required: bool = True) -> Any:
    matches = [c for c in reader.connections if c.topic == topic]
    if not matches:
        if not required:
            return None
        available = ", ".join(f"{c.topic} ({c.msgtype})" for c in reader.connections)
        raise BagError(f"topic {topic} is not in the bag (it has: {available}); choose the topic with {option}")
    if matches[0].msgtype != msgtype:
        raise BagError(f"topic {topic} holds {matches[0].msgtype}, not {msgtype}; choose another topic with {option}")
    return matches[0]


def _read_ground_truth(reader: Reader, connection: Any) -> Optional[Trajectory]:
    if connection is None:
        return None
    stamps, poses = [], []
    for c, _, raw in reader.messages(connections=[connection]):
        msg = _TYPESTORE.deserialize_cdr(raw, c.msgtype)
        stamps.append(stamp_to_sec(msg.header.stamp))
        poses.append(msg_to_pose(msg.pose))
    if not stamps:
        return None
    order = np.argsort(stamps, kind="stable")
    return Trajectory(np.asarray(stamps)[order], np.stack(poses)[order])


def _ground_truth_at(gt: Optional[Trajectory], stamp: float, tolerance: float = 1e-3) -> Optional[np.ndarray]:
    """The ground-truth pose stamped within `tolerance` seconds of `stamp`, if any."""
    if gt is None:
        return None
    i = int(np.clip(np.searchsorted(gt.timestamps, stamp), 1, len(gt) - 1)) if len(gt) > 1 else 0
    best = min((j for j in (i - 1, i) if 0 <= j < len(gt)), key=lambda j: abs(gt.timestamps[j] - stamp))
    return gt.poses[best].copy() if abs(gt.timestamps[best] - stamp) <= tolerance else None


def run_bag(
    bag: Path | str,
    cfg: Config,
    out_dir: Path | str,
    *,
    topics: BagTopics = BagTopics(),
    workers: int = 1,
    policy: str = "offline",
    depth_scale: Optional[float] = None,
    sync_queue_size: int = 10,
    sync_max_interval: Optional[float] = 0.02,
    write_mesh: bool = True,
    progress: bool = True,
    odometry: Optional[BagOdometry] = None,
) -> BagRunSummary:
    """Feed a bag through the node's input pipeline (pairing, conversion, checks) into the SLAM runtime.

    `odometry`: read the odometry on topics.odometry as the node does in REP 105 mode (Frame.odom_pose matched to
    each image stamp; with tracking.mode external, the poses themselves); its counts go into summary.json.

    Deterministic with the offline policy: every frame is tracked, in order. Writes what `eslam run` writes:
    config.yaml, trajectory.txt, groundtruth.txt (when the bag has ground truth), checkpoint.pt, mesh.ply and
    summary.json. Frames get the bag's ground-truth pose (as `eslam run` gives a data set's), so the trajectory
    starts at the first ground-truth pose and the ATE is computed.
    """
    from eslam_core.runtime import make_runtime
    from eslam_ros.input_pipeline import InputPipeline, configured_intrinsics

    out_dir = Path(out_dir)
    fixed = configured_intrinsics(cfg)
    pipeline = InputPipeline(queue_size=sync_queue_size, max_interval=sync_max_interval, depth_scale=depth_scale,
                             fixed_intrinsics=fixed, time_jump_reset=None)
    reader = _open_reader(bag)
    try:
        rgb_c = _find_connection(reader, topics.rgb, IMAGE_TYPE, "--rgb-topic")
        depth_c = _find_connection(reader, topics.depth, IMAGE_TYPE, "--depth-topic")
        info_c = _find_connection(reader, topics.camera_info, INFO_TYPE, "--info-topic", required=fixed is None)
        gt = _read_ground_truth(reader, _find_connection(reader, topics.ground_truth, POSE_TYPE, "--gt-topic",
                                                         required=False))
        odom_c = _find_connection(reader, topics.odometry, ODOMETRY_TYPE, "--odom-topic") if odometry else None
        robot = _bag_robot_odometry(odometry, cfg) if odometry else None
        out_dir.mkdir(parents=True, exist_ok=True)
        save_config(cfg, out_dir / "config.yaml")
        bar = tqdm(total=rgb_c.msgcount, desc="eslam bag run", unit="frame", disable=not progress,
                   dynamic_ncols=True)
        runtime, frames, start = None, 0, time.perf_counter()
        try:
            for accepted in _accepted_frames(reader, rgb_c, depth_c, info_c, pipeline, odom_c, robot,
                                             cfg.tracking.mode == "external"):
                if runtime is None:
                    runtime = make_runtime(cfg, accepted.intrinsics, workers=workers, policy=policy)
                    runtime.start()
                pose = _ground_truth_at(gt, accepted.frame.timestamp)
                pose = accepted.frame.pose if pose is None else pose  # without ground truth: the odometry seed
                runtime.submit(dataclasses.replace(accepted.frame, pose=pose))
                frames += 1
                bar.update(len(runtime.poll()))
            if runtime is None:
                raise BagError(f"no frame of {bag} could be used (skipped: {pipeline.skipped}, unpaired: "
                               f"{pipeline.unpaired}); see the warnings above")
        finally:
            if runtime is not None:
                runtime.close(drain=True)  # every submitted frame is tracked before the runtime stops
        seconds = time.perf_counter() - start
    finally:
        reader.close()

    timestamps, poses = runtime.trajectory()
    bar.update(len(timestamps) - bar.n)
    bar.close()
    runtime.save_trajectory(out_dir / "trajectory.txt")
    runtime.save_checkpoint(out_dir / "checkpoint.pt")
    mesh_path = None
    if write_mesh and cfg.mesh.enabled:
        try:
            mesh_path = runtime.save_mesh(out_dir / "mesh.ply")
        except ValueError as error:  # an empty map: reported, the other outputs stand
            log.error("no mesh written: %s", error)
    rmse = _write_ground_truth_and_ate(gt, timestamps, poses, out_dir)
    summary = BagRunSummary(out_dir, frames, seconds, seconds / max(frames, 1), rmse, dict(pipeline.skipped),
                            pipeline.unpaired, mesh_path)
    record = {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(summary).items()}
    if robot is not None:
        record["odometry"] = dict(robot.counts)
    record.update({"bag": str(resolve_bag(bag)), "topics": dataclasses.asdict(topics), "workers": workers,
                   "policy": policy, "frames_per_second": frames / seconds if seconds > 0 else None,
                   "config_file": str(out_dir / "config.yaml")})
    (out_dir / "summary.json").write_text(json.dumps(record, indent=2))
    return summary


def _bag_robot_odometry(odometry: BagOdometry, cfg: Config) -> Any:
    """The node's odometry input (REP 105 mode, odometry topic, extrinsic parameter) for a bag run."""
    from eslam_ros.node_params import NodeSettings
    from eslam_ros.robot_odometry import RobotOdometry
    from eslam_ros.tf_chain import select_setup

    settings = NodeSettings(odom_frame=odometry.odom_frame, base_frame=odometry.base_frame, odom_source="topic",
                            base_to_camera=tuple(float(v) for v in odometry.base_to_camera)).validate()
    return RobotOdometry(settings, select_setup(settings, have_tf2_ros=False, have_tf2_msgs=False))


def _accepted_frames(reader: Reader, rgb_c: Any, depth_c: Any, info_c: Any, pipeline: Any, odom_c: Any = None,
                     robot: Any = None, external: bool = False) -> Iterator[Any]:
    """The bag's messages in recorded order through the input pipeline: the frames it accepts (skips are logged).

    With an odometry (`robot`, fed from `odom_c`), frames come out once their odometry is settled, bag time
    standing for the clock (a frame waits for odometry until the bag is `odom.wait` s past its stamp)."""
    from eslam_ros.input_pipeline import AcceptedFrame, SkippedInput

    streams = {rgb_c.id: 0, depth_c.id: 1}
    wanted = [rgb_c, depth_c] + ([info_c] if info_c is not None else []) + ([odom_c] if odom_c is not None else [])

    def frames_of(pipeline_events: Sequence[Any], now: float, flush: bool = False) -> Iterator[Any]:
        for event in pipeline_events:
            if isinstance(event, SkippedInput):
                log.warning("%s", event.message)
            elif isinstance(event, AcceptedFrame):
                if robot is None:
                    yield event
                else:  # it waits for its odometry
                    robot.push(event.frame.timestamp, event.frame_id, event, now)
        if robot is not None:
            yield from robot.settled(now, flush, external, lambda kind, message: log.warning("%s", message))

    now = 0.0
    for c, t, raw in reader.messages(connections=wanted):
        now = t / 1e9
        msg = _TYPESTORE.deserialize_cdr(raw, c.msgtype)
        if odom_c is not None and c.id == odom_c.id:
            refused = robot.add_message(msg, now)
            if refused:
                log.warning("%s", refused)
            yield from frames_of([], now)
        elif c.id in streams:
            yield from frames_of(pipeline.add_image(streams[c.id], msg), now)
        else:
            yield from frames_of(pipeline.add_camera_info(msg), now)
    yield from frames_of(pipeline.flush(), now, flush=True)


def _write_ground_truth_and_ate(gt: Optional[Trajectory], timestamps: np.ndarray, poses: np.ndarray,
                                out_dir: Path) -> Optional[float]:
    """Write groundtruth.txt for the tracked frames that have ground truth; return the ATE RMSE (cm) over them."""
    if gt is None or len(timestamps) == 0:
        return None
    truth = [_ground_truth_at(gt, t) for t in timestamps]
    known = np.array([p is not None for p in truth])
    if not known.any():
        return None
    estimate = Trajectory(np.asarray(timestamps)[known], np.asarray(poses)[known])
    reference = Trajectory(estimate.timestamps, np.stack([p for p in truth if p is not None]))
    write_tum(out_dir / "groundtruth.txt", reference)
    return 100.0 * ate(estimate, reference, max_dt=1e-3).rmse if len(estimate) >= 3 else None


# ================================================================================================= command line


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="eslam bag", description="rosbag2 tools: write a data set as a bag, play a "
                                                              "bag on ROS 2 topics, run SLAM on a bag")
    sub = p.add_subparsers(dest="action", required=True)

    w = sub.add_parser("write", help="write a data set (TUM, ICL-NUIM, Replica, ScanNet, 7-Scenes) as a bag")
    w.add_argument("dataset", help="data set folder")
    w.add_argument("out", help="bag to create: NAME.mcap (MCAP) or NAME.db3 (sqlite3); the bag is the folder NAME")
    w.add_argument("--kind", default="auto", help="data set kind (auto, tum, icl, replica, scannet, 7scenes)")
    w.add_argument("--frames", type=parse_frames, default=(0, None), help="A:B, frames to write (default all)")
    w.add_argument("--stride", type=int, default=1, help="write every N-th frame")
    w.add_argument("--fps", type=float, default=30.0,
                   help="frame rate of data sets timed by frame number (ICL-NUIM, Replica); default 30")
    w.add_argument("--storage", choices=sorted(STORAGE_PLUGINS), help="storage (default: from the suffix, else mcap)")
    w.add_argument("--depth-encoding", default="16UC1", choices=["16UC1", "32FC1"],
                   help="16UC1 = millimetres (default), 32FC1 = metres")
    w.add_argument("--odometry", action="store_true", help="also write the ground truth as exact wheel odometry "
                                                           "(nav_msgs/Odometry odom -> base_link on /odom)")

    y = sub.add_parser("play", help="publish a bag's messages on their topics (headless player)")
    y.add_argument("bag", help="bag folder or .mcap / .db3 file")
    y.add_argument("--rate", type=float, default=1.0, help="speed factor (1 = recorded pace; 0 = as fast as the "
                                                           "subscribers acknowledge)")
    y.add_argument("--loop", action="store_true", help="start over at the end, until interrupted")
    y.add_argument("--wait", type=float, default=10.0, help="seconds to wait for subscribers first (default 10)")
    y.add_argument("--topics", nargs="+", help="play only these topics")
    y.add_argument("--qos", default="reliable", choices=["reliable", "sensor_data"], help="publisher QoS")
    y.add_argument("--wait-ready", metavar="NODE", help="also wait (up to --wait s) until this SLAM node (e.g. "
                                                        "/slam_node) reports ready on its ~/status")

    r = sub.add_parser("run", help="run SLAM on a bag: synchronizer + core, no DDS, deterministic")
    r.add_argument("bag", help="bag folder or .mcap / .db3 file")
    r.add_argument("--config", required=True, help=f"YAML file or preset name ({', '.join(list_presets())})")
    r.add_argument("--out", required=True, help="output folder")
    r.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config value")
    r.add_argument("--workers", type=int, default=1, help="SLAM processes (1 = in-process, 2 = tracking + mapping)")
    r.add_argument("--policy", default="offline", choices=["offline", "live"],
                   help="offline (default): every frame, in order; live: drop frames while busy")
    r.add_argument("--rgb-topic", default=BagTopics.rgb)
    r.add_argument("--depth-topic", default=BagTopics.depth)
    r.add_argument("--info-topic", default=BagTopics.camera_info)
    r.add_argument("--gt-topic", default=BagTopics.ground_truth)
    r.add_argument("--odometry", action="store_true", help="use the bag's odometry (--odom-topic) as the node does "
                                                           "in REP 105 mode (motion prior; the pose itself with "
                                                           "--set tracking.mode=external)")
    r.add_argument("--odom-topic", default=BagTopics.odometry)
    for sub_parser in (w, r):
        sub_parser.add_argument("--base-to-camera", type=float, nargs=7, default=list(FORWARD_CAMERA),
                                metavar=("X", "Y", "Z", "QX", "QY", "QZ", "QW"),
                                help="the camera optical frame in base_link (default: 10 cm ahead, 30 cm up, "
                                     "looking forward)")
    r.add_argument("--depth-scale", type=float, help="depth units per metre (default: by encoding, 16UC1 = mm)")
    r.add_argument("--max-interval", type=float, default=0.02, help="largest rgb-depth stamp difference (s)")
    r.add_argument("--no-mesh", action="store_true", help="skip mesh extraction")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    if args.action == "write":
        dataset = open_dataset(args.dataset, args.kind).subset(args.frames[0], args.frames[1], args.stride)
        s = write_bag(dataset, args.out, storage=args.storage, fps=args.fps, depth_encoding=args.depth_encoding,
                      progress=True, odometry=BagOdometry(base_to_camera=tuple(args.base_to_camera)) if
                      args.odometry else None)
        print(f"{s.frames} frames ({s.ground_truth_poses} ground-truth poses, {s.duration_s:.2f} s) -> {s.path} "
              f"({s.storage})")
        return 0
    if args.action == "play":
        from eslam_ros.qos import use_shipped_fastdds_profile

        use_shipped_fastdds_profile()  # large images over shared memory: the publisher's segment must fit them
        try:
            s = play_bag(args.bag, rate=args.rate, passes=0 if args.loop else 1, wait_for_subscribers=args.wait,
                         topics=args.topics, qos=args.qos, wait_ready=args.wait_ready)
        except KeyboardInterrupt:
            return 130
        print(f"published {s.messages} messages in {s.seconds:.1f} s ({s.loops} pass(es))")
        return 0
    from eslam_core.runtime import RuntimeCrashed

    cfg = load_config(args.config, parse_overrides(args.set))
    topics = BagTopics(args.rgb_topic, args.depth_topic, args.info_topic, args.gt_topic, args.odom_topic)
    try:
        s = run_bag(args.bag, cfg, args.out, topics=topics, workers=args.workers, policy=args.policy,
                    depth_scale=args.depth_scale, sync_max_interval=args.max_interval or None,
                    write_mesh=not args.no_mesh, progress=not args.quiet,
                    odometry=BagOdometry(base_to_camera=tuple(args.base_to_camera)) if args.odometry else None)
    except RuntimeCrashed as error:
        print(f"eslam bag run: the SLAM runtime crashed: {error}", file=sys.stderr)
        return 1
    ate_text = "n/a (no ground truth)" if s.ate_rmse_cm is None else f"{s.ate_rmse_cm:.2f} cm"
    print(f"{s.frames} frames, {s.seconds_per_frame:.2f} s/frame, ATE RMSE {ate_text}, skipped "
          f"{sum(s.skipped.values())}, unpaired {sum(s.unpaired.values())} -> {s.out_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
