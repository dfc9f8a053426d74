"""The node in a robot's graph, over DDS: /diagnostics and readiness, the offline start-up queue, every lifecycle
transition, and a bag with odometry replayed into slam_node in REP 105 mode (map -> odom closing the chain,
stamps, frames, QoS)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Odometry, Path as PathMsg
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image

from eslam_core.datasets import open_dataset
from eslam_core.datasets.synthetic import generate_scene
from eslam_core.datasets.tum import read_tum
from eslam_ros.bag import FORWARD_CAMERA, BagOdometry, write_bag
from eslam_ros.conversions import camera_info_from_intrinsics, depth_to_image, msg_to_pose, rgb_to_image, \
    stamp_to_sec
from eslam_ros.node_params import NodeParameterError
from eslam_ros.node_threads import spin_once
from eslam_ros.slam_node import SlamNode, start_node
from eslam_ros.tf_chain import pose_from_xyz_quaternion, transform_to_pose

REPO = Path(__file__).resolve().parent.parent
CAMERA = "camera_color_optical_frame"
BASE_CAMERA = pose_from_xyz_quaternion(FORWARD_CAMERA)
SMALL_SLAM = {"workers": 1, "preset": "fast", "eslam.mapping.iterations": 4, "eslam.mapping.rays": 600,
              "eslam.mapping.first_iterations": 60, "mesh_period": 0.0, "save_on_shutdown": False}


def _domain() -> int:
    return 1 + (os.getpid() + 37) % 101


@pytest.fixture
def ros(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    rclpy.init(domain_id=_domain())
    yield
    rclpy.try_shutdown()


def _overrides(values: dict) -> list:
    return [Parameter(name, value=value) for name, value in values.items()]


class Spinner:
    """Spins nodes on a background executor (the SLAM node needs two threads, as in its main)."""

    def __init__(self, *nodes: Node) -> None:
        self.executor = MultiThreadedExecutor(num_threads=3)
        for node in nodes:
            self.executor.add_node(node)
        self._stop = False
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while not self._stop:
            spin_once(self.executor, 0.05)

    def close(self) -> None:
        self._stop = True
        self.thread.join(5)
        self.executor.shutdown(timeout_sec=0)


def _until(condition, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return False


class Camera:
    """Publishes frames of a sequence as a driver would (rgb8, 16UC1 mm, camera info), reliable."""

    def __init__(self, node: Node, sequence, topics=("rgb/image", "depth/image", "rgb/camera_info")) -> None:
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.sequence = sequence
        self.rgb = node.create_publisher(Image, topics[0], qos)
        self.depth = node.create_publisher(Image, topics[1], qos)
        self.info = node.create_publisher(CameraInfo, topics[2], qos)

    def matched(self) -> bool:
        return all(p.get_subscription_count() for p in (self.rgb, self.depth, self.info))

    def publish(self, i: int, stamp: float) -> None:
        frame = self.sequence[i]
        self.info.publish(camera_info_from_intrinsics(self.sequence.intrinsics, stamp, CAMERA))
        self.rgb.publish(rgb_to_image(frame.rgb, stamp, CAMERA))
        self.depth.publish(depth_to_image(frame.depth, stamp, CAMERA))


def _values(status: DiagnosticStatus) -> dict:
    return {kv.key: kv.value for kv in status.values}


# ================================================================================================= diagnostics


def test_diagnostics_name_the_silent_inputs_and_report_ready_once_the_camera_is_there(ros, tmp_path):
    node = start_node(parameter_overrides=_overrides({
        **SMALL_SLAM, "status_period": 0.1, "diagnostics.no_input_timeout": 0.5, "output_dir": str(tmp_path),
        "diagnostics.hardware_id": "d435i"}))
    watcher = Node("diagnostics_watcher")
    received = []
    watcher.create_subscription(DiagnosticArray, "/diagnostics", received.append, 10)
    spinner = Spinner(node, watcher)
    try:
        assert _until(lambda: any("no input for" in m.status[0].message for m in received), 10.0), \
            [m.status[0].message for m in received]
        warned = next(m for m in received if "no input for" in m.status[0].message).status[0]
        assert warned.level == DiagnosticStatus.WARN and "rgb/image, depth/image" in warned.message
        assert (warned.name, warned.hardware_id) == ("slam_node: ESLAM", "d435i")
        values = _values(warned)
        assert values["ready"] == "False" and values["runtime"] == "waiting"
        assert values["tf_mode"].startswith("camera mode: map ->")
        assert float(values["seconds_since_rgb/image".replace("/", "_")]) >= 0.5
        # A camera appears: the node sees a publisher on every input and reports ready (before any frame).
        camera = Camera(watcher, None)
        assert _until(lambda: _values(received[-1].status[0])["ready"] == "True", 10.0)
        assert {m.status[0].name for m in received} == {"slam_node: ESLAM"}  # stable: aggregators group by it
        assert camera.matched()
    finally:
        spinner.close()
        watcher.destroy_node()
        node.destroy_node()


# ================================================================================================= start-up queue


@pytest.fixture(scope="module")
def long_sequence(tmp_path_factory):
    """40 small frames of the synthetic room: more than the 30 the node used to keep while starting."""
    path = generate_scene(tmp_path_factory.mktemp("room40") / "seq", n_frames=40, width=80, height=60, seed=5)
    return open_dataset(path, "tum")


def test_offline_policy_keeps_every_frame_that_arrives_while_the_runtime_starts(ros, long_sequence, tmp_path):
    """40 frames reach the node while the two-process runtime spawns its workers (seconds; the old limit kept 30
    and dropped the rest): each gets a pose."""
    sequence = long_sequence
    n = len(sequence)
    node = start_node(parameter_overrides=_overrides({
        **SMALL_SLAM, "workers": 2, "policy": "offline", "input_qos": "reliable", "input_queue_depth": 200,
        "output_dir": str(tmp_path)}))
    driver = Node("camera_driver")
    camera = Camera(driver, sequence)
    poses = []
    driver.create_subscription(PoseStamped, "/slam_node/pose", poses.append, 100)
    spinner = Spinner(node, driver)
    try:
        assert _until(lambda: camera.matched() and driver.count_publishers("/slam_node/pose") > 0, 10.0)
        stamps = sequence.timestamps()
        for i in range(n):  # at once: all of them arrive while the runtime starts
            camera.publish(i, stamps[i])
        assert _until(lambda: len(poses) == n, 300.0), (len(poses), node.health())
        health = node.health()
        assert health["frames_dropped_while_starting"] == 0
        frame_bytes = sequence[0].rgb.nbytes + sequence[0].depth.nbytes
        assert health["start_queue_peak_bytes"] > 30 * frame_bytes, health  # more than the old 30 waited
        assert health["start_queue_budget_bytes"] == 512 * 2**20 and health["start_queue_bytes"] == 0
        np.testing.assert_allclose([stamp_to_sec(p.header.stamp) for p in poses], stamps, atol=1e-6)
    finally:
        spinner.close()
        driver.destroy_node()
        node.finish(save=False)  # stops the worker processes
        node.destroy_node()


# ================================================================================================= lifecycle


class LifecycleClient:
    """`ros2 lifecycle set / get` from another node: the node's lifecycle services."""

    def __init__(self, node: Node, target: str) -> None:
        from lifecycle_msgs.srv import ChangeState, GetState

        self._change = node.create_client(ChangeState, f"{target}/change_state")
        self._get = node.create_client(GetState, f"{target}/get_state")
        self._request = ChangeState.Request
        assert self._change.wait_for_service(10.0) and self._get.wait_for_service(10.0)

    def set(self, transition: int) -> bool:
        from lifecycle_msgs.msg import Transition

        future = self._change.call_async(self._request(transition=Transition(id=transition)))
        assert _until(future.done, 180.0), "no answer to the transition"
        return future.result().success

    def get(self) -> int:
        from lifecycle_msgs.srv import GetState

        future = self._get.call_async(GetState.Request())
        assert _until(future.done, 10.0)
        return future.result().current_state.id


def test_every_lifecycle_transition_keeps_the_map_until_cleanup_saves_it(ros, room_sequence, tmp_path):
    from lifecycle_msgs.msg import State, Transition

    sequence = room_sequence.subset(0, 9)
    stamps = sequence.timestamps()
    out = tmp_path / "out"
    node = SlamNode(parameter_overrides=_overrides({
        **SMALL_SLAM, "policy": "offline", "input_qos": "reliable", "input_queue_depth": 100, "output_dir": str(out),
        "save_on_shutdown": True, "status_period": 0.1}))
    driver = Node("camera_driver")
    camera = Camera(driver, sequence)
    poses, status = [], []
    driver.create_subscription(PoseStamped, "/slam_node/pose", poses.append, 100)
    driver.create_subscription(DiagnosticArray, "/slam_node/status", status.append, 10)
    spinner = Spinner(node, driver)
    lifecycle = LifecycleClient(driver, "/slam_node")
    try:
        assert lifecycle.get() == State.PRIMARY_STATE_UNCONFIGURED
        assert not node.configured and node.parameters_open  # unconfigured: parameters may still change
        assert node.set_parameters([Parameter("sync.queue_size", value=12)])[0].successful
        assert lifecycle.set(Transition.TRANSITION_CONFIGURE)
        assert lifecycle.get() == State.PRIMARY_STATE_INACTIVE
        assert node.settings.sync_queue_size == 12 and not camera.matched()  # no input while inactive
        assert not node.set_parameters([Parameter("sync.queue_size", value=13)])[0].successful
        assert _until(lambda: status and "inactive" in status[-1].status[0].message, 10.0)

        assert lifecycle.set(Transition.TRANSITION_ACTIVATE) and lifecycle.get() == State.PRIMARY_STATE_ACTIVE
        assert _until(lambda: camera.matched() and node.ready(), 10.0)  # both ends see each other
        for i in range(4):
            camera.publish(i, stamps[i])
        assert _until(lambda: len(poses) == 4, 120.0), (len(poses), node.health())
        runtime = node.runtime

        assert lifecycle.set(Transition.TRANSITION_DEACTIVATE) and lifecycle.get() == State.PRIMARY_STATE_INACTIVE
        assert _until(lambda: not camera.matched(), 10.0)
        camera.publish(4, stamps[4])  # nobody listens: not taken
        time.sleep(0.5)
        assert node.runtime is runtime and len(node.runtime.trajectory()[0]) == 4  # the map and trajectory stay
        assert node.pipeline.pairs == 4

        assert lifecycle.set(Transition.TRANSITION_ACTIVATE)
        assert _until(lambda: camera.matched() and node.ready(), 10.0)
        for i in range(5, 9):
            camera.publish(i, stamps[i])
        assert _until(lambda: len(poses) == 8, 120.0), (len(poses), node.health())
        timestamps, _ = node.runtime.trajectory()
        assert node.runtime is runtime and len(timestamps) == 8  # the same map went on
        np.testing.assert_allclose(timestamps, np.delete(stamps, 4), atol=1e-6)

        assert lifecycle.set(Transition.TRANSITION_DEACTIVATE)
        assert lifecycle.set(Transition.TRANSITION_CLEANUP)  # saves as a shutdown does
        assert lifecycle.get() == State.PRIMARY_STATE_UNCONFIGURED
        assert node.runtime is None and node.exit_status == 0
        for name in ("trajectory.txt", "checkpoint.pt", "mesh.ply"):
            assert (out / name).is_file(), name
        assert len(read_tum(out / "trajectory.txt")) == 8

        assert lifecycle.set(Transition.TRANSITION_CONFIGURE)  # again, with the kept parameters
        assert node.settings.sync_queue_size == 12
        assert lifecycle.set(Transition.TRANSITION_INACTIVE_SHUTDOWN)
        assert lifecycle.get() == State.PRIMARY_STATE_FINALIZED and node.lifecycle_state == "finalized"
    finally:
        spinner.close()
        driver.destroy_node()
        node.destroy_node()


@pytest.mark.parametrize("shutdown_from", ["unconfigured", "active"])
def test_a_bad_parameter_fails_configure_and_shutdown_ends_the_node_from_any_state(ros, shutdown_from):
    from lifecycle_msgs.msg import State, Transition

    node = SlamNode(parameter_overrides=_overrides({**SMALL_SLAM, "policy": "fast"}))  # not a policy
    driver = Node("lifecycle_manager")
    spinner = Spinner(node, driver)
    lifecycle = LifecycleClient(driver, "/slam_node")
    try:
        assert not lifecycle.set(Transition.TRANSITION_CONFIGURE)  # refused, and says why
        assert lifecycle.get() == State.PRIMARY_STATE_UNCONFIGURED and "'policy' = 'fast'" in node.configure_error
        if shutdown_from == "active":
            assert node.set_parameters([Parameter("policy", value="live")])[0].successful  # fixed while unconfigured
            assert lifecycle.set(Transition.TRANSITION_CONFIGURE) and lifecycle.set(Transition.TRANSITION_ACTIVATE)
            assert lifecycle.get() == State.PRIMARY_STATE_ACTIVE
        shutdown = {"unconfigured": Transition.TRANSITION_UNCONFIGURED_SHUTDOWN,
                    "active": Transition.TRANSITION_ACTIVE_SHUTDOWN}[shutdown_from]
        assert lifecycle.set(shutdown)
        assert lifecycle.get() == State.PRIMARY_STATE_FINALIZED and node.exit_status == 0
    finally:
        spinner.close()
        driver.destroy_node()
        node.destroy_node()


def test_the_plain_node_is_active_through_its_lifecycle(ros):
    from lifecycle_msgs.msg import State

    node = start_node(parameter_overrides=_overrides(SMALL_SLAM))
    driver = Node("observer")
    spinner = Spinner(node, driver)
    try:
        assert LifecycleClient(driver, "/slam_node").get() == State.PRIMARY_STATE_ACTIVE and node.active
    finally:
        spinner.close()
        driver.destroy_node()
        node.destroy_node()
    with pytest.raises(NodeParameterError, match=r"'policy' = 'fast'"):
        start_node(parameter_overrides=_overrides({**SMALL_SLAM, "policy": "fast"}))


# ================================================================================================= REP 105 end to end


def _ros_env(domain: int) -> dict:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]), PYTHONUNBUFFERED="1")
    env.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    return env


N_E2E = 12


def test_rep105_bag_replay_closes_the_tf_chain_with_the_robots_odometry(room_sequence, tmp_path, ros):
    """slam_node (pip install: odometry topic, extrinsic parameter) fed by `eslam bag play --wait-ready` with a
    bag that has wheel odometry; poses given for the base. map -> odom composed with the odometry and the extrinsic
    is the published pose, at every stamp; the map coincides with odom at the first frame (REP 103 axes)."""
    sequence = room_sequence.subset(0, N_E2E)
    bag = write_bag(sequence, tmp_path / "robot.mcap", odometry=BagOdometry()).path
    params = {**SMALL_SLAM, "policy": "offline", "input_qos": "reliable", "input_queue_depth": 100,
              "odom_frame": "odom", "base_frame": "base_link", "base_to_camera": list(FORWARD_CAMERA),
              "pose_frame": "base", "path_period": 0.3, "status_period": 0.2, "output_dir": str(tmp_path / "out")}
    command = [sys.executable, "-m", "eslam_ros.slam_node", "--ros-args"]
    for name, value in params.items():
        command += ["-p", f"{name}:={value}"]
    for name, topic in (("rgb/image", "/camera/color/image_raw"), ("depth/image", "/camera/depth/image_raw"),
                        ("rgb/camera_info", "/camera/color/camera_info")):
        command += ["-r", f"{name}:={topic}"]
    log = open(tmp_path / "node.log", "w")
    process = subprocess.Popen(command, env=_ros_env(_domain()), cwd=REPO, stdout=log, stderr=subprocess.STDOUT,
                               start_new_session=True)
    listener = Node("robot_listener")
    got = {"pose": [], "odom": [], "map_to_odom": [], "path": [], "status": []}
    for kind, topic in ((PoseStamped, "pose"), (Odometry, "odom"), (TransformStamped, "map_to_odom"),
                        (PathMsg, "path"), (DiagnosticArray, "status")):
        listener.create_subscription(kind, f"/slam_node/{topic}", got[topic].append, 100)

    def spin_until(condition, timeout):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            rclpy.spin_once(listener, timeout_sec=0.05)
            assert process.poll() is None, (tmp_path / "node.log").read_text()[-3000:]
            if condition():
                return True
        return False

    try:
        topics = [f"/slam_node/{t}" for t in got]
        assert spin_until(lambda: got["status"] and all(listener.count_publishers(t) for t in topics), 60.0)
        values = _values(got["status"][-1].status[0])
        assert "REP 105 mode" in values["tf_mode"] and "nav_msgs/Odometry" in values["tf_mode"]
        assert "REP 105 mode" in (tmp_path / "node.log").read_text()  # said once in the log too
        player = subprocess.run([sys.executable, "-m", "eslam_core", "bag", "play", str(bag), "--wait", "60",
                                 "--wait-ready", "/slam_node", "--rate", "2"], env=_ros_env(_domain()), cwd=REPO,
                                capture_output=True, text=True, timeout=180)
        assert player.returncode == 0, player.stderr
        assert "did not report ready" not in player.stderr
        assert spin_until(lambda: len(got["pose"]) == N_E2E and len(got["map_to_odom"]) == N_E2E
                          and got["path"] and len(got["path"][-1].poses) == N_E2E, 180.0), \
            (len(got["pose"]), len(got["map_to_odom"]), [line for line in (tmp_path / "node.log").read_text()
                                                         .splitlines() if "odometry" in line or "WARN" in line])

        # Every output carries its input's stamp; frames follow REP 105.
        stamps = sequence.timestamps()
        for topic in ("pose", "odom", "map_to_odom"):
            np.testing.assert_allclose([stamp_to_sec(m.header.stamp) for m in got[topic]], stamps, atol=1e-6)
            assert {m.header.frame_id for m in got[topic]} == {"map"}, topic
        assert {m.child_frame_id for m in got["map_to_odom"]} == {"odom"}
        assert {m.child_frame_id for m in got["odom"]} == {"base_link"}
        np.testing.assert_allclose([stamp_to_sec(p.header.stamp) for p in got["path"][-1].poses], stamps, atol=1e-6)

        # map -> odom -> base (the bag's odometry) is the published base pose; the camera is that @ extrinsic.
        odom_base = [gt @ np.linalg.inv(BASE_CAMERA) for gt in sequence.gt_poses()]
        for k in range(N_E2E):
            map_odom = transform_to_pose(got["map_to_odom"][k].transform)
            map_base = msg_to_pose(got["pose"][k].pose)
            np.testing.assert_allclose(map_odom @ odom_base[k], map_base, atol=1e-5)
        np.testing.assert_allclose(transform_to_pose(got["map_to_odom"][0].transform), np.eye(4), atol=1e-6)
        # The map has odom's axes: the published base poses follow the odometry (here exact) closely.
        errors = [np.linalg.norm(msg_to_pose(got["pose"][k].pose)[:3, 3] - odom_base[k][:3, 3]) for k in range(N_E2E)]
        assert max(errors) < 0.05, errors
        # (the newest status may predate the last frame's odometry by a status period)
        assert spin_until(lambda: int(_values(got["status"][-1].status[0])["odom_matched"]) == N_E2E, 10.0), \
            _values(got["status"][-1].status[0])
        values = _values(got["status"][-1].status[0])
        assert int(values["odom_missing"]) == 0 and int(values["frames_dropped_while_starting"]) == 0

        # QoS as documented: poses reliable volatile, mesh transient local, /diagnostics reliable.
        def qos(topic):
            (info,) = listener.get_publishers_info_by_topic(topic)
            return info.qos_profile

        for topic in ("/slam_node/pose", "/slam_node/odom", "/slam_node/map_to_odom", "/slam_node/path"):
            assert (qos(topic).reliability, qos(topic).durability) == (ReliabilityPolicy.RELIABLE,
                                                                       DurabilityPolicy.VOLATILE), topic
        assert qos("/slam_node/mesh").durability == DurabilityPolicy.TRANSIENT_LOCAL
        assert qos("/diagnostics").reliability == ReliabilityPolicy.RELIABLE

        process.send_signal(signal.SIGINT)
        assert process.wait(120) == 0, (tmp_path / "node.log").read_text()[-3000:]
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait(10)
        log.close()
        listener.destroy_node()
