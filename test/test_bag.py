"""Bag tools: a data set written as a rosbag2 bag reads back identically, plays at its recorded pace, and runs
through the node's input pipeline into SLAM with the outputs of `eslam run`."""
from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import rclpy
import trimesh
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import CameraInfo, Image

from eslam_core.config import load_config
from eslam_core.datasets.tum import read_tum
from eslam_core.evaluation.trajectory_error import still_camera_ate
from eslam_ros.bag import (
    BagError,
    BagTopics,
    bag_folder,
    bag_timestamps,
    build_parser,
    play_bag,
    play_offset,
    resolve_bag,
    run_bag,
    write_bag,
)
from eslam_ros.conversions import image_to_depth, image_to_rgb, intrinsics_from_camera_info, msg_to_pose, \
    stamp_to_sec

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
N_FRAMES = 8
ATE_BOUND_CM = 1.5  # `run` at the test's settings: 0.2 cm


@pytest.fixture(scope="module")
def sequence(room_sequence):
    """Every second frame: 15 cm walked, so that a camera that never moves is 4 cm off."""
    return room_sequence.subset(0, 2 * N_FRAMES, 2)


@pytest.fixture(scope="module")
def bag(sequence, tmp_path_factory):
    return write_bag(sequence, tmp_path_factory.mktemp("bags") / "room.mcap").path


def _read_all(path):
    """{topic: [(bag time ns, decoded message)]} of a bag, decoded independently of the code under test."""
    out = {}
    with Reader(path) as reader:
        for connection, t, raw in reader.messages():
            out.setdefault(connection.topic, []).append((t, TYPESTORE.deserialize_cdr(raw, connection.msgtype)))
    return out


# ------------------------------------------------------------------------------------------------ write


@pytest.mark.parametrize("name, storage", [("room.mcap", "mcap"), ("room.db3", "sqlite3")])
def test_written_bag_reads_back_as_the_data_set(sequence, tmp_path, name, storage):
    summary = write_bag(sequence, tmp_path / name)
    assert summary.path == tmp_path / "room" and summary.storage == storage
    assert (summary.frames, summary.ground_truth_poses) == (N_FRAMES, N_FRAMES)
    assert (tmp_path / "room" / "metadata.yaml").is_file()
    assert list((tmp_path / "room").glob("*.mcap" if storage == "mcap" else "*.db3"))

    topics = BagTopics()
    messages = _read_all(summary.path)
    assert {k: len(v) for k, v in messages.items()} == {
        topics.rgb: N_FRAMES, topics.depth: N_FRAMES, topics.camera_info: N_FRAMES, topics.ground_truth: N_FRAMES}
    stamps = sequence.timestamps()
    gt = sequence.gt_poses()
    for i in range(N_FRAMES):
        frame = sequence[i]
        (t_rgb, rgb), (t_depth, depth) = messages[topics.rgb][i], messages[topics.depth][i]
        (_, info), (_, pose) = messages[topics.camera_info][i], messages[topics.ground_truth][i]
        # Header stamps and bag times are the data set's time stamps.
        for t_ns, msg in ((t_rgb, rgb), (t_depth, depth), (None, info), (None, pose)):
            assert abs(stamp_to_sec(msg.header.stamp) - stamps[i]) < 1e-9
            assert t_ns is None or abs(t_ns * 1e-9 - stamps[i]) < 1e-9
        assert (rgb.encoding, depth.encoding) == ("rgb8", "16UC1")
        assert rgb.header.frame_id == depth.header.frame_id == info.header.frame_id == "camera_color_optical_frame"
        np.testing.assert_array_equal(image_to_rgb(rgb), frame.rgb)
        # 16UC1 holds whole millimetres: at most half a millimetre off, and holes stay holes.
        np.testing.assert_allclose(image_to_depth(depth), frame.depth, atol=0.0005 + 1e-6)
        assert np.array_equal(image_to_depth(depth) == 0, frame.depth == 0)
        assert intrinsics_from_camera_info(info) == sequence.intrinsics
        np.testing.assert_allclose(msg_to_pose(pose.pose), gt[i], atol=1e-9)
        assert pose.header.frame_id == "world"


def test_depth_as_32fc1_keeps_metres_exactly(sequence, tmp_path):
    path = write_bag(sequence.subset(0, 2), tmp_path / "metres", depth_encoding="32FC1").path
    (_, depth), _ = _read_all(path)[BagTopics().depth]
    assert depth.encoding == "32FC1"
    np.testing.assert_array_equal(image_to_depth(depth), sequence[0].depth)


def test_frame_numbered_data_sets_are_timed_at_the_given_rate():
    icl = SimpleNamespace(kind="icl", root="x", timestamps=lambda: np.arange(1.0, 301.0))
    stamps = bag_timestamps(icl, fps=30.0)
    assert stamps[0] == pytest.approx(1 / 30) and np.allclose(np.diff(stamps), 1 / 30)
    tum = SimpleNamespace(kind="tum", root="x", timestamps=lambda: np.array([1305031102.175, 1305031102.211]))
    np.testing.assert_array_equal(bag_timestamps(tum, fps=30.0), tum.timestamps())
    backwards = SimpleNamespace(kind="tum", root="seq", timestamps=lambda: np.array([2.0, 1.0]))
    with pytest.raises(BagError, match="strictly increasing"):
        bag_timestamps(backwards, fps=30.0)


def test_bag_names_storage_and_errors(sequence, bag, tmp_path):
    assert bag_folder("a/x.mcap") == (Path("a/x"), "mcap")
    assert bag_folder("x.db3")[1] == "sqlite3" and bag_folder("x")[1] == "mcap"
    with pytest.raises(BagError, match="suffix of mcap"):
        bag_folder("x.mcap", storage="sqlite3")
    assert resolve_bag(bag.parent / "room.mcap") == bag  # the name given to `write` finds the folder
    with pytest.raises(BagError, match="bag not found"):
        resolve_bag(tmp_path / "nothing.mcap")
    with pytest.raises(BagError, match="delete it or choose another name"):
        write_bag(sequence, bag)  # never overwrites


def test_command_line_parses_the_issue_examples():
    p = build_parser()
    assert p.parse_args(["write", "data", "out.mcap"]).out == "out.mcap"
    args = p.parse_args(["play", "b", "--rate", "2", "--loop"])
    assert (args.rate, args.loop, args.qos) == (2.0, True, "reliable")
    args = p.parse_args(["run", "b", "--config", "demo", "--out", "o", "--set", "tracking.iterations=2"])
    assert (args.workers, args.policy, args.set) == (1, "offline", ["tracking.iterations=2"])


# ------------------------------------------------------------------------------------------------ play


def test_play_offsets_follow_the_recorded_pace():
    first = 1_305_031_102_175_304_000
    assert play_offset(first, first, 1.0) == 0.0
    assert play_offset(first + 400_000_000, first, 1.0) == pytest.approx(0.4)
    assert play_offset(first + 400_000_000, first, 2.0) == pytest.approx(0.2)
    assert play_offset(first + 400_000_000, first, 0.0) == 0.0


@pytest.fixture
def ros_context(monkeypatch):
    """rclpy on a domain of its own, discovery limited to this machine."""
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    rclpy.init(domain_id=1 + os.getpid() % 100)
    yield
    rclpy.try_shutdown()


def test_player_publishes_every_message_at_the_recorded_pace_and_loops(bag, sequence, ros_context):
    topics = BagTopics()
    received: dict[str, list] = {topics.rgb: [], topics.depth: [], topics.camera_info: []}
    listener = Node("bag_listener")
    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    for topic, kind in ((topics.rgb, Image), (topics.depth, Image), (topics.camera_info, CameraInfo)):
        listener.create_subscription(kind, topic, lambda m, t=topic: received[t].append((time.monotonic(), m)),
                                     reliable)
    executor = SingleThreadedExecutor()
    executor.add_node(listener)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        rate = 2.0
        summary = play_bag(bag, rate=rate, passes=2, wait_for_subscribers=10.0)
        deadline = time.monotonic() + 5.0
        while sum(map(len, received.values())) < 2 * 3 * N_FRAMES and time.monotonic() < deadline:
            time.sleep(0.05)
        # rate 0: as fast as the (reliable) subscriptions acknowledge, nothing lost.
        flat_out = play_bag(bag, rate=0.0, wait_for_subscribers=10.0)
        while sum(map(len, received.values())) < 3 * 3 * N_FRAMES and time.monotonic() < deadline + 5.0:
            time.sleep(0.05)
    finally:
        executor.shutdown()
        listener.destroy_node()

    assert summary.subscribers_found and summary.messages == 2 * 4 * N_FRAMES and summary.loops == 2
    assert all(len(v) == 3 * N_FRAMES for v in received.values()), {k: len(v) for k, v in received.items()}
    assert flat_out.messages == 4 * N_FRAMES and flat_out.seconds < 5.0
    stamps = sequence.timestamps()
    expected_span = (stamps[-1] - stamps[0]) / rate
    for one_pass in (slice(0, N_FRAMES), slice(N_FRAMES, 2 * N_FRAMES)):
        arrivals = np.array([t for t, _ in received[topics.rgb][one_pass]])
        assert abs((arrivals[-1] - arrivals[0]) - expected_span) < 0.15, (arrivals, expected_span)
        # Decoded messages, not bytes, are compared (CDR padding may differ); each pass has the bag's stamps.
        for i, (_, msg) in enumerate(received[topics.rgb][one_pass]):
            assert abs(stamp_to_sec(msg.header.stamp) - stamps[i]) < 1e-9
            np.testing.assert_array_equal(image_to_rgb(msg), sequence[i].rgb)


# ------------------------------------------------------------------------------------------------ run


def _fast_config():
    """Small settings: the pipeline and the outputs are under test here, not SLAM accuracy at full settings."""
    return load_config("fast", {"mapping": {"iterations": 3, "rays": 500, "first_iterations": 40},
                                "mesh": {"resolution": 0.05}})


def test_run_writes_the_outputs_of_eslam_run(bag, sequence, tmp_path):
    out = tmp_path / "run"
    summary = run_bag(bag, _fast_config(), out, progress=False)

    assert summary.frames == N_FRAMES and sum(summary.skipped.values()) == 0
    assert summary.unpaired == {"unpaired_rgb": 0, "unpaired_depth": 0}
    for name in ("config.yaml", "trajectory.txt", "groundtruth.txt", "checkpoint.pt", "mesh.ply", "summary.json"):
        assert (out / name).is_file(), name
    trajectory, gt = read_tum(out / "trajectory.txt"), read_tum(out / "groundtruth.txt")
    np.testing.assert_allclose(trajectory.timestamps, sequence.timestamps(), atol=1e-6)
    # The first pose is the bag's ground truth, as with `eslam run`: outputs share the ground truth's frame.
    np.testing.assert_allclose(trajectory.poses[0], sequence.gt_poses()[0], atol=1e-5)
    np.testing.assert_allclose(gt.poses, np.stack(sequence.gt_poses()), atol=1e-6)
    assert ATE_BOUND_CM < 0.5 * 100 * still_camera_ate(gt.positions)
    assert summary.ate_rmse_cm is not None and summary.ate_rmse_cm < ATE_BOUND_CM
    assert json.loads((out / "summary.json").read_text())["frames"] == N_FRAMES
    assert len(trimesh.load(out / "mesh.ply").faces) > 100


def test_run_names_missing_topics(bag, tmp_path):
    with pytest.raises(BagError, match=r"/cam/rgb is not in the bag .*--rgb-topic"):
        run_bag(bag, _fast_config(), tmp_path / "x", topics=BagTopics(rgb="/cam/rgb"), progress=False)
