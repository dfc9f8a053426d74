"""~/mesh as incremental block markers (mesh_markers.py, mesh_publication.py), through real DDS: a changed block is
re-sent with the same id, an unchanged one is not, an emptied one is deleted, a late subscriber gets every block;
and the node keeps publishing poses from a 30 Hz stream while its mesh is being built."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CameraInfo, Image
from visualization_msgs.msg import Marker, MarkerArray

from eslam_ros.conversions import camera_info_from_intrinsics, depth_to_image, rgb_to_image
from eslam_ros import mesh_publication
from eslam_ros.mesh_markers import (CORNER_BYTES, TriangleBlock, block_marker_id, block_message_parts,
                                    serialize_block_markers)
from eslam_ros.mesh_publication import MeshPublication
from eslam_ros.qos import latched_qos
from test_mesh_blocks import BALL, BLOCK, RES, SMALL, snapshot_of

REPO = Path(__file__).resolve().parent.parent
LATCHED = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)


def _domain() -> int:
    # Not test_ros_node's domains (1..101): a node of a test there, still shutting down, must not answer here.
    return 102 + os.getpid() % 100


@pytest.fixture
def ros(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    rclpy.init(domain_id=_domain())
    yield
    rclpy.try_shutdown()


class Viewer:
    """What RViz does with MarkerArray messages: ADD replaces the marker of that (ns, id), DELETE removes it,
    DELETEALL removes all."""

    def __init__(self, node: Node, qos=LATCHED) -> None:
        self.messages: list[MarkerArray] = []
        self.markers: dict[int, Marker] = {}
        node.create_subscription(MarkerArray, "/mesh_test", self._on_message, qos)

    def _on_message(self, msg: MarkerArray) -> None:
        self.messages.append(msg)
        for marker in msg.markers:
            if marker.action == Marker.DELETEALL:
                self.markers.clear()
            elif marker.action == Marker.DELETE:
                self.markers.pop(marker.id, None)
            else:
                self.markers[marker.id] = marker


def test_block_markers_decode_with_ids_from_block_coordinates():
    rng = np.random.default_rng(0)
    corners = rng.uniform(-1, 1, (9, 3))
    colors = rng.uniform(0, 1, (9, 4)).astype(np.float32)
    blocks = {(1, -1, 1): TriangleBlock(corners, colors), (-3, 0, 2): TriangleBlock(corners[:3], None)}
    msg = deserialize_message(serialize_block_markers(blocks, [(0, 0, -1)], "map", 12.5, ns="m", delete_all=True),
                              MarkerArray)
    actions = [(m.action, m.id) for m in msg.markers]
    assert actions == [(Marker.DELETEALL, 0), (Marker.DELETE, block_marker_id((0, 0, -1))),
                       (Marker.ADD, block_marker_id((1, -1, 1))), (Marker.ADD, block_marker_id((-3, 0, 2)))]
    added = msg.markers[2]
    assert added.type == Marker.TRIANGLE_LIST and added.header.frame_id == "map" and added.ns == "m"
    np.testing.assert_array_equal([[p.x, p.y, p.z] for p in added.points], corners)
    np.testing.assert_allclose([[c.r, c.g, c.b, c.a] for c in added.colors], colors)
    assert len(msg.markers[3].points) == 3 and not msg.markers[3].colors
    # Ids: distinct for neighbouring and negative coordinates, stable, within int32.
    keys = [(i, j, k) for i in range(-3, 4) for j in range(-3, 4) for k in range(-3, 4)]
    ids = {block_marker_id(key) for key in keys}
    assert len(ids) == len(keys) and all(0 <= i < 2**31 for i in ids)


def test_submaps_blocks_are_markers_in_a_namespace_per_submap():
    corners = np.zeros((3, 3))
    blocks = {(0, 1, -1, 1): TriangleBlock(corners, None), (3, 1, -1, 1): TriangleBlock(corners, None)}
    msg = deserialize_message(serialize_block_markers(blocks, [(3, 0, 0, 0)], "map", 1.0, ns="m"), MarkerArray)
    assert [(m.action, m.ns, m.id) for m in msg.markers] == [
        (Marker.DELETE, "m/submap_3", block_marker_id((0, 0, 0))),
        (Marker.ADD, "m/submap_0", block_marker_id((1, -1, 1))), (Marker.ADD, "m/submap_3", block_marker_id((1, -1, 1)))]


def test_blocks_are_cut_into_messages_of_at_most_the_size_asked():
    blocks = {(i, 0, 0): TriangleBlock(np.zeros((3 * n, 3)), None) for i, n in enumerate([100, 300, 50, 2000, 10])}
    parts = block_message_parts(blocks, 500 * 3 * CORNER_BYTES)
    assert [list(part) for part in parts] == [[(0, 0, 0), (1, 0, 0), (2, 0, 0)], [(3, 0, 0)], [(4, 0, 0)]]
    for part in parts:  # the estimate is the message's size, to within the fixed fields of each marker
        size = len(serialize_block_markers(part, [], "map", 0.0))
        assert size <= 500 * 3 * CORNER_BYTES + 300 * len(part) or len(part) == 1
    assert block_message_parts({}, 1000) == [{}]


def test_a_large_update_comes_in_several_messages_and_a_full_one_in_one(monkeypatch):
    """Updates over MAX_MESSAGE_BYTES are cut (rclpy holds the interpreter lock while it publishes one message, and
    the node's poses wait); a full update stays one message (the last message must hold the whole map)."""
    monkeypatch.setattr(mesh_publication, "MAX_MESSAGE_BYTES", 1)  # every block a message of its own
    sent: list[MarkerArray] = []
    publication = MeshPublication(lambda data: sent.append(deserialize_message(data, MarkerArray)), "map",
                                  lambda: 0.0, rclpy.logging.get_logger("mesh_test"), resolution=RES,
                                  block_size=BLOCK, period=0.0, budget_s=1e9, triangle_budget=10**6, rest_s=1e9)

    def step_until(condition, timeout=60.0):
        deadline = time.monotonic() + timeout
        while not condition() and time.monotonic() < deadline:
            publication.step(1, lambda have: None)
            time.sleep(0.02)
        return condition()

    try:
        publication.step(1, lambda have: snapshot_of([BALL, SMALL], have))
        assert step_until(lambda: sent and not publication.mesher.busy), publication.status()
        ids = [m.id for message in sent for m in message.markers]
        assert len(sent) >= 6 and all(len(message.markers) == 1 for message in sent)
        assert len(set(ids)) == len(ids) and {m.action for message in sent for m in message.markers} == {Marker.ADD}
        assert publication.status()["meshes_published"] == len(sent)

        count = len(sent)
        publication.subscriber_matched(None)  # a newcomer: every block, in one message
        assert step_until(lambda: len(sent) > count and not publication.mesher.busy)
        assert len(sent) == count + 1 and sorted(m.id for m in sent[-1].markers) == sorted(ids)
    finally:
        publication.close()


def test_the_mesh_process_rests_between_jobs_for_its_duty():
    """At duty 0.25 a job of t seconds is followed by 3 t seconds without one (its work slows the tracker even at
    SCHED_IDLE); the map is still meshed completely, one job after another."""
    updates: list[tuple[float, float]] = []  # (time published, wall seconds of its job)

    def publish(data: bytes) -> None:
        updates.append((time.monotonic(), publication.figures.job_ms_last / 1e3))

    publication = MeshPublication(publish, "map", lambda: 0.0, rclpy.logging.get_logger("mesh_test"), resolution=RES,
                                  block_size=BLOCK, period=1e9, budget_s=0.02, triangle_budget=10**6, duty=0.25,
                                  rest_s=1e9)
    try:
        publication.step(1, lambda have: snapshot_of([BALL, SMALL], have))
        deadline = time.monotonic() + 120
        while (publication.mesher.busy or publication.mesher.pending) and time.monotonic() < deadline:
            publication.step(1, lambda have: None)
            time.sleep(0.002)
        assert not publication.mesher.pending and len(updates) >= 3, publication.status()
        for (published, job_s), (next_published, _) in zip(updates, updates[1:]):
            assert next_published - published >= 3 * job_s * 0.95
    finally:
        publication.close()
    with pytest.raises(ValueError, match="duty"):
        MeshPublication(lambda data: None, "map", lambda: 0.0, None, resolution=RES, block_size=BLOCK, period=1.0,
                        budget_s=1.0, triangle_budget=1, duty=0.0)


def test_only_changed_blocks_are_sent_and_a_late_subscriber_gets_them_all(ros):
    pub_node, sub_node = Node("mesh_test_publisher"), Node("mesh_test_viewer")
    executor = SingleThreadedExecutor()
    executor.add_node(pub_node)
    executor.add_node(sub_node)
    publication: MeshPublication = None

    def matched(status):
        publication.subscriber_matched(status)

    publisher = pub_node.create_publisher(MarkerArray, "/mesh_test", latched_qos(),
                                          event_callbacks=PublisherEventCallbacks(matched=matched))
    publication = MeshPublication(publisher.publish, "map", lambda: pub_node.get_clock().now().to_msg(),
                                  pub_node.get_logger(), resolution=RES, block_size=BLOCK, period=0.0, budget_s=1e9,
                                  triangle_budget=10**6, rest_s=1e9)
    viewer = Viewer(sub_node)

    def spin_until(condition, timeout=60.0):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.02)
            if condition():
                return True
        return False

    def publish_map(version, balls) -> MarkerArray:
        """One snapshot of the map, stepped until its update is published; the message it caused."""
        count = len(viewer.messages)
        publication.step(version, lambda have: snapshot_of(balls, have))
        assert spin_until(lambda: publication.step(version, lambda have: None) or len(viewer.messages) > count), \
            publication.status()
        assert not publication.mesher.busy and len(viewer.messages) == count + 1
        return viewer.messages[-1]

    try:
        assert spin_until(lambda: publisher.get_subscription_count() == 1)
        first = publish_map(1, [BALL, SMALL])
        assert {m.action for m in first.markers} == {Marker.ADD} and len(first.markers) >= 6
        assert {m.id for m in first.markers} == set(viewer.markers)
        small_id = block_marker_id((1, -1, 1))
        assert small_id in viewer.markers
        before = {i: len(m.points) for i, m in viewer.markers.items()}

        # The small ball grows: its block alone is re-sent, with its id; every other block is not.
        grown = publish_map(2, [BALL, (SMALL[0], SMALL[1], SMALL[2], SMALL[3] + 0.03)])
        assert [(m.action, m.id) for m in grown.markers] == [(Marker.ADD, small_id)]
        assert len(viewer.markers[small_id].points) > before[small_id]

        # It vanishes: its block is deleted (a DELETE with the same id), nothing else is sent, no DELETEALL.
        gone = publish_map(3, [BALL])
        assert [(m.action, m.id) for m in gone.markers] == [(Marker.DELETE, small_id)]
        assert set(viewer.markers) == set(before) - {small_id}

        # A subscriber that comes now gets every block in one message (after the last delta, its history).
        late = Viewer(sub_node)
        assert spin_until(lambda: (publication.step(3, lambda have: None) or True) and late.messages
                          and late.markers.keys() == viewer.markers.keys())
        assert publication.status()["mesh_full_publications"] == 1
        assert all(len(late.markers[i].points) == len(viewer.markers[i].points) for i in viewer.markers)

        # The ball comes back (a delta), then nothing changes: once at rest, every block in one message, so that
        # the last message (what transient local keeps, what a bridge caches for its next client) is complete.
        back = publish_map(4, [BALL, SMALL])
        assert [(m.action, m.id) for m in back.markers] == [(Marker.ADD, small_id)]
        publication.rest_s = 0.0
        assert spin_until(lambda: publication.step(4, lambda have: None) or len(viewer.messages) > 5)
        assert {m.id for m in viewer.messages[-1].markers} == set(viewer.markers) == set(before)
        assert publication.status()["mesh_full_publications"] == 2
        spin_until(lambda: publication.step(4, lambda have: None), timeout=0.5)
        assert len(viewer.messages) == 6  # once

        # A reset: one DELETEALL, and every viewer is empty.
        publication.reset()
        assert spin_until(lambda: not viewer.markers and not late.markers)
        assert [m.action for m in viewer.messages[-1].markers] == [Marker.DELETEALL]
        status = publication.status()
        assert status["meshes_published"] == 7 and status["mesh_blocks"] == 0 and status["mesh_job_cpu_ms_last"] > 0
    finally:
        publication.close()
        pub_node.destroy_node()
        sub_node.destroy_node()


# ------------------------------------------------------------------------------------------------ the node


def _ros_env(domain: int) -> dict:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]), PYTHONUNBUFFERED="1")
    env.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    return env


def test_node_keeps_publishing_poses_from_a_30_hz_stream_while_its_mesh_is_built(room_sequence, ros, tmp_path):
    """A fine mesh (1 cm voxels, jobs of up to 3 s) is built while about 2.5 s of a 30 Hz camera stream arrive: poses
    keep coming at the tracker's pace, without a gap, during the mesh jobs."""
    params = {"workers": 2, "policy": "live", "input_qos": "reliable", "preset": "fast", "save_on_shutdown": False,
              "mesh_period": 0.2, "mesh_resolution": 0.01, "mesh_time_budget": 3.0, "status_period": 0.1,
              "output_dir": str(tmp_path / "out"), "eslam.mapping.first_iterations": 60}
    command = [sys.executable, "-m", "eslam_ros.slam_node", "--ros-args"]
    for name, value in params.items():
        command += ["-p", f"{name}:={value}"]
    for name, topic in (("rgb/image", "/cam/rgb"), ("depth/image", "/cam/depth"), ("rgb/camera_info", "/cam/info")):
        command += ["-r", f"{name}:={topic}"]
    log_path = tmp_path / "node.log"
    with open(log_path, "w") as log:
        process = subprocess.Popen(command, env=_ros_env(_domain()), cwd=REPO, stdout=log, stderr=subprocess.STDOUT,
                                   start_new_session=True)
    node = Node("stream_test")
    poses, status = [], []
    node.create_subscription(PoseStamped, "/slam_node/pose", lambda m: poses.append(time.monotonic()), 100)
    node.create_subscription(DiagnosticArray, "/slam_node/status", lambda m: status.append(
        (time.monotonic(), {kv.key: kv.value for kv in m.status[0].values})), 100)
    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    rgb_pub, depth_pub = node.create_publisher(Image, "/cam/rgb", reliable), node.create_publisher(Image, "/cam/depth",
                                                                                                    reliable)
    info_pub = node.create_publisher(CameraInfo, "/cam/info", reliable)

    def spin_for(seconds: float, until=lambda: False) -> bool:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.005)
            assert process.poll() is None, "the node died: " + log_path.read_text()[-3000:]
            if until():
                return True
        return False

    # Forwards, backwards, forwards: a smooth 90-frame camera path out of the 30 frames, stamps at 30 Hz.
    order = list(range(30)) + list(range(28, -1, -1)) + list(range(1, 30))
    frames = [room_sequence[i] for i in range(30)]

    def send(k: int) -> None:
        frame, stamp = frames[order[k]], 100.0 + k / 30.0
        info_pub.publish(camera_info_from_intrinsics(room_sequence.intrinsics, stamp, "cam"))
        rgb_pub.publish(rgb_to_image(frame.rgb, stamp, "cam"))
        depth_pub.publish(depth_to_image(frame.depth, stamp, "cam"))

    try:
        # The node's topics are volatile: wait until they reach us (its status does) before anything is published.
        assert spin_for(60.0, lambda: rgb_pub.get_subscription_count() and depth_pub.get_subscription_count()
                        and info_pub.get_subscription_count() and node.count_publishers("/slam_node/pose")
                        and status)
        # The first frame starts the runtime and the map; then a frame every 0.2 s until one is tracked against the
        # fitted map (frames that come during the warm-up may be dropped by the live policy).
        send(0)
        assert spin_for(120.0, lambda: status and status[-1][1].get("runtime") == "running"
                        and int(status[-1][1].get("map_version", 0)) >= 1), log_path.read_text()[-3000:]
        k, deadline = 1, time.monotonic() + 120.0
        while not (status and int(status[-1][1].get("poses_published", 0)) >= 2):
            assert time.monotonic() < deadline and k < 40, (
                {key: v for key, v in status[-1][1].items() if key.startswith(("frames", "pairs", "poses", "map_"))}
                if status else None, log_path.read_text()[-3000:])
            send(k)
            k += 1
            spin_for(0.2)
        # Then the mesh of that map is being built: stream the rest of the frames meanwhile.
        assert spin_for(60.0, lambda: status and status[-1][1].get("mesh_busy") == "True"), log_path.read_text()[-3000:]
        start, first = time.monotonic(), k
        for k in range(first, len(order)):
            send(k)
            spin_for(start + (k - first + 1) / 30.0 - time.monotonic())
        end = time.monotonic()
        # Once the stream is over the mesh process gets the CPU, and the mesh arrives.
        spin_for(120.0, lambda: status and int(status[-1][1].get("meshes_published", 0)) >= 1)
    finally:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
        node.destroy_node()

    streamed = [t for t in poses if start <= t <= end]
    busy = [t for t, values in status if start <= t <= end and values.get("mesh_busy") == "True"]
    final = status[-1][1]
    log = log_path.read_text()[-3000:]
    # A mesh was being built for at least 0.8 s of the stream (status every 0.1 s; how long depends on the CPU the
    # tracker leaves it), and it was published once the CPU was free again ...
    assert len(busy) >= 8 and int(final["meshes_published"]) >= 1, (len(busy), final, log)
    # ... while poses kept coming, at a quarter of the camera's rate or more while the mesh was built, never a second
    # without one (a mesh job lasts seconds: a node that waited for it would stall that long).
    during = [t for t in streamed if busy[0] <= t <= busy[-1]]
    assert len(during) >= 0.25 * 30 * (busy[-1] - busy[0]), (len(during), busy[-1] - busy[0], log)
    gaps = np.diff([start] + streamed + [end])
    assert len(streamed) >= 10 and gaps.max() < 1.0, (len(streamed), gaps.max(), log)
