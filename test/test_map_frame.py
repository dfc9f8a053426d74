"""The map frame squared with the scene (mapping/map_frame.py): normals of depth, the scene's axes, the turn."""
from __future__ import annotations

import numpy as np
import pytest

from eslam_core.camera import Frame
from eslam_core.config import load_config
from eslam_core.datasets.synthetic import build_room, default_intrinsics, frame_rng, look_at, render_frame
from eslam_core.frames import pixel_directions_table, prepare_frame
from eslam_core.geometry import rotation_angle_deg, rotvec_to_matrix
from eslam_core.mapping.map_frame import depth_normals, squared_first_pose, squaring_rotation, surface_axes
from eslam_core.tracking.frontend import TrackingFrontEnd
from eslam_core.trajectory import TrackedTrajectory

INTR = default_intrinsics(320, 240)


def _plane_depth(normal, distance: float) -> np.ndarray:
    """Depth of the plane {x: normal . x = distance} (camera frame) at every pixel."""
    v, u = np.mgrid[0:INTR.height, 0:INTR.width]
    rays = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones(u.shape)], axis=-1)
    return (distance / (rays @ np.asarray(normal))).astype(np.float32)


def _off_signed_permutation_deg(rotation: np.ndarray) -> float:
    """Angle (degrees) between `rotation` and the signed permutation nearest to it."""
    nearest = np.zeros((3, 3))
    for row in range(3):
        column = np.argmax(np.abs(rotation[row]))
        nearest[row, column] = np.sign(rotation[row, column])
    return rotation_angle_deg(rotation @ nearest.T)


@pytest.fixture(scope="module")
def room():
    return build_room()


def _tilted_camera() -> np.ndarray:
    """A camera in the room looking into a corner, pitched down and rolled: none of its axes along the room's."""
    return look_at(eye=(-1.2, -0.8, 1.5), target=(1.0, 1.0, 0.6), roll_rad=np.radians(12))


def test_normals_of_a_plane_are_its_normal():
    normal = rotvec_to_matrix(np.radians([20.0, -30.0, 0.0])) @ np.array([0.0, 0.0, -1.0])
    normals = depth_normals(_plane_depth(normal, -2.0), INTR)
    assert len(normals) > 1000
    assert np.degrees(np.arccos(np.abs(normals @ normal).min())) < 0.1


def test_the_squared_frame_puts_the_rooms_floor_and_walls_along_the_map_axes(room):
    camera_to_room = _tilted_camera()
    assert _off_signed_permutation_deg(camera_to_room[:3, :3]) > 20  # not squared to start with
    _, depth = render_frame(room, INTR, camera_to_room, frame_rng(0, 0))  # with sensor noise and holes
    pose = squared_first_pose(depth, INTR)
    assert np.allclose(pose[:3, 3], 0.0) and np.allclose(pose[3], [0, 0, 0, 1])
    room_to_map = pose[:3, :3] @ camera_to_room[:3, :3].T
    assert _off_signed_permutation_deg(room_to_map) < 1.5
    assert rotation_angle_deg(pose[:3, :3]) < 60  # the nearest squared frame, not an arbitrary one


def test_a_single_plane_is_squared_by_the_smallest_tilt():
    tilt = 25.0
    normal = rotvec_to_matrix(np.radians([tilt, 0.0, 0.0])) @ np.array([0.0, 0.0, -1.0])
    axes = surface_axes(depth_normals(_plane_depth(normal, -2.0), INTR))
    assert axes is not None
    rotation = squaring_rotation(axes)
    assert abs(rotation_angle_deg(rotation) - tilt) < 0.5
    assert abs(abs(rotation @ normal)[2] - 1.0) < 1e-4  # the wall faces the map's z axis


def test_a_view_without_dominant_surfaces_keeps_the_cameras_frame():
    v, u = np.mgrid[0:INTR.height, 0:INTR.width]
    x, y = (u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy
    # the near half of a ball of radius 0.8 m, 2 m ahead, filling the view: its normals spread evenly
    b = x**2 + y**2 + 1.0
    disc = (2.0**2) - b * (2.0**2 - 0.8**2)
    depth = np.where(disc > 0, (2.0 - np.sqrt(np.maximum(disc, 0))) / b, 0.0).astype(np.float32)
    assert surface_axes(depth_normals(depth, INTR)) is None
    assert np.array_equal(squared_first_pose(depth, INTR), np.eye(4))


def test_the_front_end_squares_the_first_pose_only_without_ground_truth_or_bound(room):
    camera_to_room = _tilted_camera()
    rgb, depth = render_frame(room, INTR, camera_to_room, frame_rng(0, 0))

    def first_pose(overrides: dict, gt_pose=None) -> np.ndarray:
        cfg = load_config("demo", overrides)
        frontend = TrackingFrontEnd(cfg, INTR, pixel_directions_table(INTR))
        frame = prepare_frame(Frame(0, 0.0, rgb, depth, gt_pose), INTR, cfg.camera)
        return frontend.first_pose(frame, TrackedTrajectory())

    squared = first_pose({})
    assert _off_signed_permutation_deg(squared[:3, :3] @ camera_to_room[:3, :3].T) < 1.5
    assert np.allclose(first_pose({}, gt_pose=camera_to_room), camera_to_room, atol=1e-6)
    assert np.array_equal(first_pose({"scene": {"align_axes": False}}), np.eye(4))
    assert np.array_equal(first_pose({"scene": {"bound": [[-3, -3, -3], [3, 3, 3]]}}), np.eye(4))
