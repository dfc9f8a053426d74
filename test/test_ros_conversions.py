"""Message conversions (images, camera info, poses, stamps) and the fast mesh MarkerArray serialiser."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from rclpy.serialization import deserialize_message, serialize_message
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, Image
from visualization_msgs.msg import Marker, MarkerArray

from eslam_core.camera import Intrinsics
from eslam_core.geometry import orthonormalize
from eslam_ros.conversions import (
    InvalidCameraInfoError,
    InvalidPoseError,
    InvalidStampError,
    MalformedImageError,
    UnsupportedImageError,
    camera_info_from_intrinsics,
    depth_to_image,
    image_to_depth,
    image_to_rgb,
    intrinsics_from_camera_info,
    msg_to_pose,
    pose_to_msg,
    rgb_to_image,
    sec_to_stamp,
    stamp_to_sec,
)
from eslam_ros.mesh_markers import (
    InvalidMeshError,
    mesh_to_marker_array,
    select_triangles,
    serialize_mesh_marker_array,
)

RNG = np.random.default_rng(7)
H, W = 5, 7


def _hand_made_image(pixels: np.ndarray, encoding: str, big_endian: bool, padding: int) -> Image:
    """Image with `padding` garbage bytes after each row, written independently of the module under test."""
    dtype = pixels.dtype.newbyteorder(">" if big_endian else "<")
    rows = pixels.astype(dtype).reshape(pixels.shape[0], -1).view(np.uint8)
    garbage = np.full((rows.shape[0], padding), 0xAB, dtype=np.uint8)
    data = np.hstack([rows, garbage])
    return Image(
        height=pixels.shape[0], width=pixels.shape[1], encoding=encoding, is_bigendian=int(big_endian),
        step=data.shape[1], data=data.tobytes(),
    )


# ------------------------------------------------------------------------------------------------ colour


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8"])
def test_colour_round_trip_for_every_encoding(encoding):
    rgb = RNG.integers(0, 256, (H, W, 3), dtype=np.uint8)
    msg = rgb_to_image(rgb, 1.5, "camera_color_optical_frame", encoding)
    assert (msg.encoding, msg.height, msg.width, msg.step) == (encoding, H, W, W * len(encoding.rstrip("8")))
    assert msg.header.frame_id == "camera_color_optical_frame" and msg.header.stamp.nanosec == 500_000_000
    out = image_to_rgb(msg)
    assert out.dtype == np.uint8 and out.shape == (H, W, 3)
    np.testing.assert_array_equal(out, rgb)
    # The result is a copy: the message buffer can be reused by the middleware.
    assert not np.shares_memory(out, np.frombuffer(msg.data, np.uint8))


def test_mono8_replicates_grey_and_stores_luma():
    grey = RNG.integers(0, 256, (H, W), dtype=np.uint8)
    rgb = np.repeat(grey[..., None], 3, axis=2)
    np.testing.assert_array_equal(image_to_rgb(rgb_to_image(rgb, 0.0, "cam", "mono8")), rgb)
    colour = np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255]]], dtype=np.uint8)
    luma = np.frombuffer(rgb_to_image(colour, 0.0, "cam", "mono8").data, np.uint8)
    np.testing.assert_array_equal(luma, [76, 150, 29])  # 0.299, 0.587, 0.114 of 255


@pytest.mark.parametrize("encoding, order", [("rgb8", [0, 1, 2]), ("bgr8", [2, 1, 0]), ("bgra8", [2, 1, 0, 3])])
def test_colour_with_row_padding(encoding, order):
    rgba = RNG.integers(0, 256, (H, W, 4), dtype=np.uint8)
    msg = _hand_made_image(np.ascontiguousarray(rgba[..., order]), encoding, big_endian=False, padding=5)
    np.testing.assert_array_equal(image_to_rgb(msg), rgba[..., :3])


# ------------------------------------------------------------------------------------------------ depth


@pytest.mark.parametrize("encoding", ["16UC1", "mono16"])
@pytest.mark.parametrize("big_endian", [False, True])
def test_16bit_depth_is_millimetres_with_padding_and_either_byte_order(encoding, big_endian):
    mm = RNG.integers(0, 10_000, (H, W)).astype(np.uint16)
    mm[0, :3] = 0
    msg = _hand_made_image(mm[..., None], encoding, big_endian, padding=3)
    depth = image_to_depth(msg)
    assert depth.dtype == np.float32 and depth.shape == (H, W)
    np.testing.assert_allclose(depth, mm / 1000.0, rtol=1e-6)
    assert np.all(depth[0, :3] == 0)
    # A data set with another unit (e.g. TUM's 5000 per metre) passes its scale.
    np.testing.assert_allclose(image_to_depth(msg, depth_scale=5000.0), mm / 5000.0, rtol=1e-6)


def test_16uc1_round_trip_is_exact_to_the_millimetre():
    mm = RNG.integers(1, 65_536, (H, W))
    depth = (mm / 1000.0).astype(np.float32)
    msg = depth_to_image(depth, 3.0, "cam", "16UC1")
    np.testing.assert_array_equal(np.frombuffer(msg.data, "<u2").reshape(H, W), mm)
    np.testing.assert_array_equal(np.round(image_to_depth(msg) * 1000.0), mm)


def test_16uc1_writer_maps_missing_and_out_of_range_depth_to_zero():
    depth = np.array([[np.nan, np.inf, -1.0, 0.0, 70.0, 65.535, 0.0004, 0.0006]], dtype=np.float32)
    stored = np.frombuffer(depth_to_image(depth, 0.0, "cam").data, "<u2")
    np.testing.assert_array_equal(stored, [0, 0, 0, 0, 0, 65535, 0, 1])


@pytest.mark.parametrize("big_endian", [False, True])
def test_32fc1_depth_in_metres_with_nan_inf_and_negative_as_missing(big_endian):
    raw = RNG.uniform(0.3, 8.0, (H, W)).astype(np.float32)
    raw[0, :5] = [np.nan, np.inf, -np.inf, -2.0, 0.0]
    msg = _hand_made_image(raw[..., None], "32FC1", big_endian, padding=2)  # step not a multiple of 4
    depth = image_to_depth(msg)
    np.testing.assert_array_equal(depth[0, :5], 0.0)
    np.testing.assert_array_equal(depth[1:], raw[1:])


def test_32fc1_round_trip_writes_nan_for_missing():
    depth = RNG.uniform(0.3, 8.0, (H, W)).astype(np.float32)
    depth[2, 3] = 0.0
    msg = depth_to_image(depth, 0.0, "cam", "32FC1")
    assert math.isnan(np.frombuffer(msg.data, "<f4")[2 * W + 3])
    np.testing.assert_array_equal(image_to_depth(msg), depth)


# ------------------------------------------------------------------------------------------------ bad images


def test_malformed_and_unsupported_images_raise_clear_errors():
    good = rgb_to_image(RNG.integers(0, 256, (H, W, 3), dtype=np.uint8), 0.0, "cam")

    truncated = rgb_to_image(np.zeros((H, W, 3), np.uint8), 0.0, "cam")
    truncated.data = bytes(good.data)[:-1]
    with pytest.raises(MalformedImageError, match=r"104 bytes but step \* height = 21 \* 5 = 105"):
        image_to_rgb(truncated)

    narrow = rgb_to_image(np.zeros((H, W, 3), np.uint8), 0.0, "cam")
    narrow.step = W * 3 - 1
    with pytest.raises(MalformedImageError, match=r"step 20 bytes is smaller than width \* bytes per pixel = 7 \* 3"):
        image_to_rgb(narrow)

    yuv = rgb_to_image(np.zeros((H, W, 3), np.uint8), 0.0, "cam")
    yuv.encoding = "yuv422"
    with pytest.raises(UnsupportedImageError, match="'yuv422'.*rgb8, bgr8, rgba8, bgra8, mono8"):
        image_to_rgb(yuv)
    with pytest.raises(UnsupportedImageError, match="'rgb8'.*16UC1, mono16, 32FC1"):
        image_to_depth(good)
    with pytest.raises(UnsupportedImageError, match="32FC1"):
        image_to_rgb(depth_to_image(np.ones((H, W)), 0.0, "cam", "32FC1"))
    with pytest.raises(MalformedImageError, match="H x W x 3 uint8"):
        rgb_to_image(np.zeros((H, W, 3), np.float32), 0.0, "cam")
    with pytest.raises(UnsupportedImageError, match="16UC1"):
        depth_to_image(np.ones((H, W)), 0.0, "cam", "8UC1")


def test_messages_read_from_a_bag_with_rosbags_convert_too():
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_JAZZY)
    rgb = RNG.integers(0, 256, (H, W, 3), dtype=np.uint8)
    image_bytes = serialize_message(rgb_to_image(rgb, 3.25, "cam", "bgr8"))
    image = typestore.deserialize_cdr(image_bytes, "sensor_msgs/msg/Image")
    np.testing.assert_array_equal(image_to_rgb(image), rgb)
    assert stamp_to_sec(image.header.stamp) == 3.25
    depth_bytes = serialize_message(depth_to_image(np.full((H, W), 1.234), 0.0, "cam"))
    depth = typestore.deserialize_cdr(depth_bytes, "sensor_msgs/msg/Image")
    np.testing.assert_allclose(image_to_depth(depth), 1.234, rtol=1e-6)


# ------------------------------------------------------------------------------------------------ camera info


def test_camera_info_round_trip():
    intr = Intrinsics(width=640, height=480, fx=525.0, fy=526.5, cx=319.5, cy=239.25)
    msg = camera_info_from_intrinsics(intr, 12.25, "camera_color_optical_frame")
    assert msg.header.frame_id == "camera_color_optical_frame" and stamp_to_sec(msg.header.stamp) == 12.25
    np.testing.assert_array_equal(np.reshape(msg.p, (3, 4))[:, :3], intr.matrix())
    # Through the wire format, as a subscriber gets it.
    received = deserialize_message(serialize_message(msg), CameraInfo)
    assert intrinsics_from_camera_info(received) == intr


def test_camera_info_with_binning_and_roi_describes_the_smaller_image():
    msg = camera_info_from_intrinsics(Intrinsics(640, 480, 500.0, 500.0, 320.0, 240.0), 0.0, "cam")
    msg.binning_x = msg.binning_y = 2
    msg.roi.x_offset, msg.roi.y_offset, msg.roi.width, msg.roi.height = 100, 40, 400, 300
    assert intrinsics_from_camera_info(msg) == Intrinsics(200, 150, 250.0, 250.0, 110.0, 100.0)


def test_uncalibrated_camera_info_is_rejected():
    msg = CameraInfo(width=640, height=480)
    with pytest.raises(InvalidCameraInfoError, match="all zeros.*calibrate"):
        intrinsics_from_camera_info(msg)
    msg.k = [500.0, 0, 320, 0, 500, 240, 0, 0, 1]
    msg.width = 0
    with pytest.raises(InvalidCameraInfoError, match="camera size"):
        intrinsics_from_camera_info(msg)


# ------------------------------------------------------------------------------------------------ poses, stamps


def test_pose_round_trip_for_random_and_half_turn_rotations():
    half_turns = [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
    rotations = list(Rotation.random(200, random_state=3).as_matrix()) + half_turns + [np.eye(3)]
    for rotation in rotations:
        pose = np.eye(4)
        pose[:3, :3] = rotation
        pose[:3, 3] = RNG.uniform(-5, 5, 3)
        msg = pose_to_msg(pose)
        q = [msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w]
        reference = Rotation.from_matrix(rotation).as_quat()  # (x, y, z, w), independent implementation
        assert min(np.abs(q - reference).max(), np.abs(q + reference).max()) < 1e-9
        np.testing.assert_allclose(msg_to_pose(msg), pose, atol=1e-9)


def test_bad_poses_raise():
    with pytest.raises(InvalidPoseError, match="4x4"):
        pose_to_msg(np.eye(3))
    with pytest.raises(InvalidPoseError, match="NaN"):
        pose_to_msg(np.full((4, 4), np.nan))
    with pytest.raises(InvalidPoseError, match="rigid"):
        pose_to_msg(np.diag([2.0, 2.0, 2.0, 1.0]))
    with pytest.raises(InvalidPoseError, match="rigid"):
        pose_to_msg(np.diag([1.0, 1.0, -1.0, 1.0]))  # a reflection
    zero = pose_to_msg(np.eye(4))
    zero.orientation.w = 0.0
    with pytest.raises(InvalidPoseError, match="quaternion"):
        msg_to_pose(zero)


def _drift(rotation: np.ndarray) -> float:
    """How far a matrix is from a rotation: max |R^T R - I|."""
    r = np.asarray(rotation, dtype=np.float64)
    return float(np.abs(r.T @ r - np.eye(3)).max())


def test_published_poses_stay_orthonormal_over_10000_composed_updates():
    """A tracker composes small motions into its pose in float32, here to first order (R (I + [w]x), not a rotation):
    unchecked, the pose drifts away from a rotation without bound. Re-orthonormalised where it is made (as the
    tracking front end does with geometry.orthonormalize) and published by pose_to_msg, every one of 10,000 poses
    is published, as a rotation, and keeps to the composed motion."""
    rng = np.random.default_rng(0)
    unchecked = np.eye(4, dtype=np.float32)
    pose = np.eye(4, dtype=np.float32)
    worst_published, worst_gap, worst_made, worst_shift = 0.0, 0.0, 0.0, 0.0
    for _ in range(10_000):
        w, t = rng.normal(0.0, 0.01, 3), rng.normal(0.0, 0.005, 3)
        motion = np.eye(4)
        motion[:3, :3] += [[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]]
        motion[:3, 3] = t
        unchecked = (unchecked @ motion).astype(np.float32)
        pose = orthonormalize((pose @ motion).astype(np.float32)).astype(np.float32)
        worst_made = max(worst_made, _drift(pose[:3, :3]))
        published = msg_to_pose(pose_to_msg(pose))
        worst_published = max(worst_published, _drift(published[:3, :3]))
        worst_gap = max(worst_gap, float(np.abs(published[:3, :3] - pose[:3, :3]).max()))  # ~ radians
        worst_shift = max(worst_shift, float(np.abs(published[:3, 3] - pose[:3, 3]).max()))
    assert _drift(unchecked[:3, :3]) > 1.0  # what first-order updates do unchecked
    assert worst_made < 1e-5 and worst_published < 1e-12 and worst_gap < 1e-5 and worst_shift == 0.0
    # A pose ten times further from orthonormal than the old refusal threshold (1e-4) is published as its rotation.
    drifted = np.eye(4)
    drifted[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix() * (1 + 5e-4)
    msg = pose_to_msg(drifted)
    back = msg_to_pose(msg)
    assert _drift(back[:3, :3]) < 1e-12
    np.testing.assert_allclose(back[:3, :3], Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix(), atol=1e-9)


def test_a_path_with_a_broken_pose_still_carries_the_others():
    from nav_msgs.msg import Path as PathMsg

    from eslam_ros.conversions import path_cdr

    poses = np.stack([np.eye(4), np.diag([2.0, 2.0, 2.0, 1.0]), np.eye(4)])  # the middle one is no rotation
    path = deserialize_message(path_cdr(np.array([1.0, 2.0, 3.0]), poses, "map"), PathMsg)
    assert [p.header.stamp.sec for p in path.poses] == [1, 3] and path.header.stamp.sec == 3
    empty = deserialize_message(path_cdr(np.zeros(0), np.zeros((0, 4, 4)), "map"), PathMsg)
    assert empty.header.frame_id == "map" and not empty.poses


@pytest.mark.parametrize("frame_id", ["map", "odom", "a_frame", "world_frame_7"])  # every padding of the records
def test_a_path_written_as_bytes_is_the_message_rclpy_builds(frame_id):
    from nav_msgs.msg import Path as PathMsg

    from eslam_ros.conversions import path_cdr
    from eslam_ros.pose_messages import pose_stamped

    rng = np.random.default_rng(len(frame_id))
    poses = np.tile(np.eye(4), (5, 1, 1))
    for pose in poses:
        pose[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        pose[:3, 3] = rng.normal(size=3)
    poses[2, :3, :3] *= 1 + 5e-4  # drifted: published as its rotation
    stamps = 1_700_000_000 + np.arange(5) / 30 + 0.123456789
    expected = PathMsg()
    expected.header.frame_id = frame_id
    expected.poses = [pose_stamped(p, sec_to_stamp(t), frame_id) for t, p in zip(stamps, poses)]
    expected.header.stamp = expected.poses[-1].header.stamp
    data = path_cdr(stamps, poses, frame_id)
    assert len(data) == len(serialize_message(expected))  # (padding bytes rclpy leaves as they were)
    assert deserialize_message(data, PathMsg) == expected  # every field, to the bit


def test_stamps_round_trip_to_the_nanosecond():
    assert (sec_to_stamp(1.5).sec, sec_to_stamp(1.5).nanosec) == (1, 500_000_000)
    assert (sec_to_stamp(-0.25).sec, sec_to_stamp(-0.25).nanosec) == (-1, 750_000_000)
    assert (sec_to_stamp(2.9999999999).sec, sec_to_stamp(2.9999999999).nanosec) == (3, 0)
    stamp = Time(sec=1_700_000_000, nanosec=123_456_789)
    assert abs(stamp_to_sec(stamp) - 1_700_000_000.123456789) < 1e-6
    back = sec_to_stamp(stamp_to_sec(stamp))
    assert back.sec == stamp.sec and abs(back.nanosec - stamp.nanosec) <= 250  # float64 resolution at 1.7e9 s
    with pytest.raises(InvalidStampError, match="finite"):
        sec_to_stamp(float("nan"))
    with pytest.raises(InvalidStampError, match="int32"):
        sec_to_stamp(1e12)


# ------------------------------------------------------------------------------------------------ mesh markers


def _random_mesh(n_vertices, n_faces, channels=3):
    vertices = RNG.uniform(-2, 2, (n_vertices, 3))
    faces = RNG.integers(0, n_vertices, (n_faces, 3))
    colors = RNG.integers(0, 256, (n_vertices, channels), dtype=np.uint8)
    return vertices, faces, colors


def _decoded(data: bytes) -> MarkerArray:
    return deserialize_message(data, MarkerArray)


def _points(marker) -> np.ndarray:
    return np.array([(p.x, p.y, p.z) for p in marker.points]).reshape(-1, 3)


def _colors(marker) -> np.ndarray:
    return np.array([(c.r, c.g, c.b, c.a) for c in marker.colors], dtype=np.float32).reshape(-1, 4)


def test_100k_triangle_mesh_serialises_fast_and_decodes_to_the_same_triangles():
    vertices, faces, colors = _random_mesh(60_000, 100_000)
    serialize_mesh_marker_array(vertices, faces, colors, "map", 1.0)  # warm-up
    started = time.perf_counter()
    data = serialize_mesh_marker_array(vertices, faces, colors, "map", 42.5, ns="eslam_mesh")
    elapsed = time.perf_counter() - started
    print(f"serialised 100k triangles in {elapsed * 1000:.1f} ms ({len(data) / 1e6:.1f} MB)")
    assert elapsed < 0.5  # measured ~25 ms; loose bound against a busy machine

    markers = _decoded(data).markers
    assert len(markers) == 1 + 2  # DELETEALL + ceil(100000 / 65536) blocks
    assert markers[0].action == Marker.DELETEALL and markers[0].ns == "eslam_mesh"
    assert [len(m.points) for m in markers[1:]] == [3 * 65536, 3 * (100_000 - 65536)]
    for index, marker in enumerate(markers[1:]):
        assert (marker.type, marker.action, marker.id) == (Marker.TRIANGLE_LIST, Marker.ADD, index)
        assert marker.ns == "eslam_mesh"
        assert marker.header.frame_id == "map" and stamp_to_sec(marker.header.stamp) == 42.5
        assert marker.pose.orientation.w == 1.0 and marker.scale.x == marker.scale.y == marker.scale.z == 1.0
    points = np.vstack([_points(m) for m in markers[1:]])
    np.testing.assert_array_equal(points, vertices[faces].reshape(-1, 3))
    rgba = np.vstack([_colors(m) for m in markers[1:]])
    np.testing.assert_allclose(rgba[:, :3] * 255.0, colors[faces].reshape(-1, 3), atol=1e-3)
    assert np.all(rgba[:, 3] == 1.0)


@pytest.mark.parametrize("with_colors, channels", [(True, 4), (False, 3)])
def test_bytes_and_message_object_describe_the_same_markers(with_colors, channels):
    vertices, faces, colors = _random_mesh(30, 50, channels)
    colors = colors if with_colors else None
    args = (vertices, faces, colors, "map", Time(sec=7, nanosec=5))
    data = serialize_mesh_marker_array(*args, max_triangles_per_marker=16)
    message = mesh_to_marker_array(*args, max_triangles_per_marker=16)
    assert len(message.markers) == 1 + 4
    # Float32 fields compare equal only after both went through the wire format.
    assert _decoded(data) == _decoded(serialize_message(message))
    if colors is None:
        assert all(len(m.colors) == 0 and m.color.a == 1.0 for m in message.markers[1:])
    else:
        np.testing.assert_allclose(_colors(message.markers[1])[:, 3] * 255.0, colors[faces[:16]].reshape(-1, 4)[:, 3])


def test_triangle_budget_keeps_an_even_subset_of_faces():
    vertices, faces, colors = _random_mesh(500, 1000)
    data = serialize_mesh_marker_array(
        vertices, faces, colors, "map", 0.0, max_triangles_per_marker=128, triangle_budget=300
    )
    markers = _decoded(data).markers
    sizes = [len(m.points) // 3 for m in markers[1:]]
    assert sum(sizes) == 300 and max(sizes) <= 128 and len(markers) == 1 + 3
    kept = select_triangles(1000, 300)
    assert len(np.unique(kept)) == 300 and kept[0] == 0 and kept[-1] >= 990
    assert np.diff(kept).max() <= 4  # evenly spread: no large gap in the face list
    np.testing.assert_array_equal(np.vstack([_points(m) for m in markers[1:]]), vertices[faces[kept]].reshape(-1, 3))


def test_empty_mesh_gives_only_the_delete_all_marker():
    for data in (
        serialize_mesh_marker_array(np.zeros((0, 3)), np.zeros((0, 3), int), None, "map", 1.0),
        serialize_message(mesh_to_marker_array(np.zeros((0, 3)), np.zeros((0, 3), int), None, "map", 1.0)),
    ):
        markers = _decoded(data).markers
        assert len(markers) == 1 and markers[0].action == Marker.DELETEALL and markers[0].header.frame_id == "map"


def test_inconsistent_mesh_is_rejected():
    vertices, faces, colors = _random_mesh(10, 5)
    with pytest.raises(InvalidMeshError, match="only 10 vertices"):
        serialize_mesh_marker_array(vertices, faces + 10, None, "map", 0.0)
    with pytest.raises(InvalidMeshError, match="one per vertex"):
        serialize_mesh_marker_array(vertices, faces, colors[:5], "map", 0.0)
    with pytest.raises(InvalidMeshError, match=r"\(V, 3\)"):
        serialize_mesh_marker_array(vertices[:, :2], faces, None, "map", 0.0)
