"""~/load_map never loses the map: the node (in this process, fed over DDS, its real Trigger service) checks the
`map_file` checkpoint with every check the load makes before it lets go of its map. A damaged file, a map of other
model settings or of another camera is refused with one line and the running map goes on (poses keep coming, the
trajectory goes on growing); a good map is loaded and the camera relocalized in it (poses in its frame)."""
from __future__ import annotations

import dataclasses
import os
import shutil
import time

import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry, Path as PathMsg
from rclpy.node import Node
from scipy.spatial.transform import Rotation
from std_srvs.srv import Trigger

from eslam_core.config import load_config
from eslam_core.datasets.synthetic import default_intrinsics
from eslam_core.outputs.export import save_checkpoint
from eslam_core.slam import SLAM
from eslam_ros.conversions import msg_to_pose, stamp_to_sec
from eslam_ros.slam_node import start_node
from test_ros_robot_node import SMALL_SLAM, Camera, Spinner

MAPPED = 12  # the checkpoints map frames 0-11 of the room; the node is fed the frames after them
# The node's settings (SMALL_SLAM: the fast preset, cheap mapping), a shorter first mapping step (the checks
# compare the model settings, and a loaded map runs on with the mapping settings saved with it).
MAPPING = {"iterations": 4, "rays": 600, "first_iterations": 30}
# The good map to load is made in a frame of its own (its first pose is OFFSET @ ground truth): the node's poses
# say in which map it tracks, the one it ran (the ground truth's frame) or the one it loaded.
OFFSET = np.eye(4)
OFFSET[:3, :3] = Rotation.from_euler("z", 25.0, degrees=True).as_matrix()
OFFSET[:3, 3] = [0.4, -0.3, 0.1]


def _domain() -> int:
    return 1 + (os.getpid() + 59) % 101


def _until(condition, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return False


def _map(sequence, cfg, frames: int, offset: np.ndarray = np.eye(4)) -> SLAM:
    slam = SLAM(cfg, sequence.intrinsics)
    for i in range(frames):
        frame = sequence[i]
        slam.step(dataclasses.replace(frame, pose=offset @ frame.pose))
    return slam


@pytest.fixture(scope="module")
def maps(room_sequence, tmp_path_factory):
    """Checkpoints made with eslam_core: the node's first map, the good map in the OFFSET frame (both the node's
    settings), a map of the demo preset (other model settings), one of another camera, and a damaged copy. Also
    where the first and the good map put their last frame (MAPPED - 1): see `in_map`."""
    folder = tmp_path_factory.mktemp("maps")
    cfg = load_config("fast", {"mapping": MAPPING})
    first, good = _map(room_sequence, cfg, MAPPED), _map(room_sequence, cfg, MAPPED, OFFSET)
    files = {"first": save_checkpoint(first, folder / "first.pt"), "good": save_checkpoint(good, folder / "good.pt"),
             "first_end": first.trajectory.pose(MAPPED - 1), "good_end": good.trajectory.pose(MAPPED - 1)}
    demo = load_config("demo", {"mapping": {"first_iterations": 2, "rays": 300}})  # the replica model
    files["other_preset"] = save_checkpoint(_map(room_sequence, demo, 1), folder / "demo.pt")
    files["other_camera"] = save_checkpoint(SLAM(cfg, default_intrinsics(80, 60)), folder / "camera.pt")
    data = files["first"].read_bytes()
    (folder / "damaged.pt").write_bytes(data[: len(data) // 2])  # a copy cut short
    files["damaged"] = folder / "damaged.pt"
    return files


def in_map(maps, name: str, sequence, i: int) -> np.ndarray:
    """The true pose of frame i in the map `name`, as that map has it: the ground-truth motion from the map's last
    frame on, from where the map put that frame (the maps, made in a few seconds, are a few centimetres off at
    their end, and differently each time: the relocalization is measured, not the map)."""
    last = MAPPED - 1
    return maps[f"{name}_end"] @ np.linalg.inv(sequence[last].pose) @ sequence[i].pose


class Session:
    """The node, started from `map_file` (a copy of the first map), a camera feeding it the room's frames, and
    what it publishes."""

    def __init__(self, sequence, maps, folder) -> None:
        self.sequence, self.maps = sequence, maps
        self.map_file = folder / "map.pt"
        shutil.copyfile(maps["first"], self.map_file)
        self.node = start_node(parameter_overrides=[rclpy.parameter.Parameter(name, value=value) for name, value in {
            **SMALL_SLAM, "policy": "offline", "input_qos": "reliable", "input_queue_depth": 100,
            "path_period": 0.2, "output_dir": str(folder / "out"), "map_file": str(self.map_file)}.items()])
        self.client_node = Node("load_map_test")
        self.camera = Camera(self.client_node, sequence)
        self.odoms, self.poses, self.paths = {}, {}, []
        self.client_node.create_subscription(Odometry, "/slam_node/odom", self._stamped(self.odoms), 100)
        self.client_node.create_subscription(PoseStamped, "/slam_node/pose", self._stamped(self.poses), 100)
        self.client_node.create_subscription(PathMsg, "/slam_node/path", self.paths.append, 10)
        self.load_map = self.client_node.create_client(Trigger, "/slam_node/load_map")
        self.spinner = Spinner(self.node, self.client_node)
        self.next = MAPPED
        assert _until(lambda: self.camera.matched() and self.node.ready() and self.load_map.service_is_ready()
                      and self.client_node.count_publishers("/slam_node/odom"), 20.0)

    @staticmethod
    def _stamped(store: dict):
        return lambda msg: store.__setitem__(round(stamp_to_sec(msg.header.stamp), 6), msg)

    def stamp(self, i: int) -> float:
        return round(float(self.sequence.timestamps()[i]), 6)

    def feed(self, n: int) -> list[int]:
        """The next `n` frames of the walk, until each got its odometry (lost or not)."""
        frames = list(range(self.next, self.next + n))
        self.next += n
        for i in frames:
            self.camera.publish(i, self.stamp(i))
        assert _until(lambda: all(self.stamp(i) in self.odoms for i in frames), 120.0), \
            (frames, sorted(self.odoms), self.node.health())
        return frames

    def path_stamps(self, expected: list[int]) -> list[float]:
        """The stamps of ~/path once it holds those of `expected` (or the last one within 10 s)."""
        want = [self.stamp(i) for i in expected]

        def stamps() -> list[float]:
            return [round(stamp_to_sec(p.header.stamp), 6) for p in self.paths[-1].poses] if self.paths else []
        _until(lambda: stamps() == want, 10.0)
        return stamps()

    def call_load_map(self) -> Trigger.Response:
        future = self.load_map.call_async(Trigger.Request())
        assert _until(future.done, 60.0), "~/load_map did not answer"
        return future.result()

    def close(self) -> None:
        self.node.finish(save=False)  # (closes the node's callbacks, and the runtime)
        _stop(self.spinner)
        self.client_node.destroy_node()
        self.node.destroy_node()


def _stop(spinner: Spinner) -> None:
    """Stop spinning, and let callbacks the executor handed to its threads end before their nodes go (rclpy's
    shutdown does not wait for them: a message taken from a destroyed subscription is an error printed at exit)."""
    spinner.close()
    time.sleep(0.3)


@pytest.fixture(scope="module")
def ros():
    """rclpy in this process for the module, on a domain of its own, discovery limited to this machine."""
    before = os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE")
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    rclpy.init(domain_id=_domain())
    yield
    rclpy.try_shutdown()
    if before is None:
        os.environ.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
    else:
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = before


@pytest.fixture(scope="module")
def session(ros, room_sequence, maps, tmp_path_factory):
    """One node for the module (its start and the first relocalization are paid once): it has run frames 12-14
    in its first map when a test starts."""
    session = Session(room_sequence, maps, tmp_path_factory.mktemp("node"))
    try:
        session.feed(3)
        yield session
    finally:
        session.close()


@pytest.mark.parametrize("bad, expected", [
    ("damaged", "is damaged (truncated or corrupt archive"),
    ("other_preset", "model.fine_appearance_resolution is 0.03 in the map, 0.06 in this config"),
    ("other_camera", "was made for camera 80x60"),
])
def test_a_map_that_cannot_load_is_refused_and_the_running_map_goes_on(session, bad, expected):
    runtime = session.node.runtime
    assert runtime is not None and not session.node.failed
    shutil.copyfile(session.maps[bad], session.map_file)
    response = session.call_load_map()
    assert not response.success, response.message
    assert expected in response.message and "current map goes on" in response.message, response.message
    assert "\n" not in response.message and len(response.message) < 400, response.message
    assert str(session.map_file) in response.message

    # The same map runs on: each new frame gets a pose in it, and its trajectory holds every frame since the
    # start (the map's 12 and all the node was fed), not only those after the refusal.
    frames = session.feed(2)
    assert session.node.runtime is runtime and not session.node.failed
    assert all(session.stamp(i) in session.poses for i in frames)  # tracked, not lost
    assert session.path_stamps(list(range(session.next))) == [session.stamp(i) for i in range(session.next)]
    for i in frames:  # still where the first map has the camera
        pose = msg_to_pose(session.poses[session.stamp(i)].pose)
        assert np.linalg.norm(pose[:3, 3] - in_map(session.maps, "first", session.sequence, i)[:3, 3]) < 0.05


def test_a_good_map_is_loaded_and_the_camera_relocalized_in_it(session):
    runtime = session.node.runtime
    before = max(session.poses)  # the newest pose in the running map
    shutil.copyfile(session.maps["good"], session.map_file)
    response = session.call_load_map()
    assert response.success, response.message
    assert response.message.startswith(f"{session.map_file}: the next frame starts in this map")
    frames = session.feed(8)
    assert session.node.runtime is not runtime and not session.node.failed
    # The trajectory is the loaded map's (its 12 frames) and the frames since the load: the frames the old map
    # tracked are gone with it.
    assert session.path_stamps(list(range(MAPPED)) + frames) == [session.stamp(i)
                                                                    for i in list(range(MAPPED)) + frames]

    # The camera starts lost in the loaded map and is found in it: the poses are where that map has the camera,
    # in its frame (OFFSET from the first map's).
    found = [i for i in frames if session.stamp(i) in session.poses]
    assert frames[-1] in found and len(found) >= len(frames) // 2, found
    published = {i: msg_to_pose(session.poses[session.stamp(i)].pose) for i in found}
    truth = {i: in_map(session.maps, "good", session.sequence, i) for i in found}
    errors = {i: round(float(np.linalg.norm(published[i][:3, 3] - truth[i][:3, 3])), 4) for i in found}
    error = max(errors.values())
    # A constant pose: the loaded map's origin (its first camera), or the node's last pose before the load.
    constants = [OFFSET @ session.sequence[0].pose, msg_to_pose(session.poses[before].pose)]
    constant_error = min(np.sqrt(np.mean([np.sum((c[:3, 3] - truth[i][:3, 3]) ** 2) for i in found]))
                         for c in constants)
    assert error < 0.1 * constant_error, (errors, constant_error)
    # ... and not where the map it replaced had the camera.
    assert all(np.linalg.norm(published[i][:3, 3] - in_map(session.maps, "first", session.sequence, i)[:3, 3])
               > 0.25 for i in found)


def test_before_the_first_frame_the_camera_is_checked_when_it_comes(ros, maps, tmp_path):
    """No frame yet, so no camera: ~/load_map checks the rest, and says the camera waits for the first frame."""
    map_file = tmp_path / "map.pt"
    shutil.copyfile(maps["first"], map_file)
    node = start_node("slam_node_cold", parameter_overrides=[
        rclpy.parameter.Parameter(name, value=value) for name, value in {
            **SMALL_SLAM, "output_dir": str(tmp_path / "out"), "map_file": str(map_file)}.items()])
    caller = Node("load_map_cold_test")
    load_map = caller.create_client(Trigger, "/slam_node_cold/load_map")
    spinner = Spinner(node, caller)
    try:
        assert load_map.wait_for_service(timeout_sec=20.0)

        def call() -> Trigger.Response:
            future = load_map.call_async(Trigger.Request())
            assert _until(future.done, 60.0), "~/load_map did not answer"
            return future.result()

        shutil.copyfile(maps["other_preset"], map_file)
        response = call()
        assert not response.success and "model.fine_appearance_resolution" in response.message, response.message
        assert "nothing changed" in response.message, response.message
        shutil.copyfile(maps["other_camera"], map_file)  # its camera is the one check that has to wait
        response = call()
        assert response.success and "camera is checked against the first frame" in response.message, \
            response.message
        assert node.runtime is None and not node.failed
    finally:
        node.finish(save=False)
        _stop(spinner)
        caller.destroy_node()
        node.destroy_node()
