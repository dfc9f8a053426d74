"""The pose's information and covariance (tracking/information.py): which directions a view constrains, the step
that leaves the others alone, and a covariance whose weak axis is the free one."""
import numpy as np
import pytest
import torch

from eslam_core.camera import Intrinsics
from eslam_core.tracking.information import (PRIOR_SIGMA_M, UNCONSTRAINED_BELOW, constrained_directions,
                                             constrained_step, pose_covariance, unconstrained_part, view_information)
from eslam_core.tracking.sdf_tracker import normal_equations

CAMERA = np.array([0.4, -0.3, 1.2])


def _planes(normals, n=600, seed=0, spread=1.0):
    """Points on planes through the scene in front of CAMERA, each with its plane's normal as the residual
    gradient (an SDF residual per 1 cm Huber scale): normal equations (H, b=0), n points."""
    g = torch.Generator().manual_seed(seed)
    x, grads = [], []
    for normal in normals:
        normal = torch.tensor(normal, dtype=torch.float64)
        in_plane = torch.randn(n // len(normals), 3, generator=g, dtype=torch.float64) * spread
        in_plane -= (in_plane @ normal)[:, None] * normal
        x.append(in_plane + torch.tensor(CAMERA) + 1.5 * normal)
        grads.append(normal.expand(len(in_plane), 3) / 0.01)
    x, grads = torch.cat(x), torch.cat(grads)
    H, _ = normal_equations(x, torch.zeros(len(x), dtype=torch.float64), grads, torch.ones(len(x), dtype=torch.float64))
    return H.numpy(), len(x)


def test_a_box_corner_constrains_every_direction():
    H, n = _planes([(1, 0, 0), (0, 1, 0), (0, 0, 1)])
    information, _, constrained = constrained_directions(H, n, CAMERA, 1.5)
    assert constrained.all() and information[0] > 10 * UNCONSTRAINED_BELOW


@pytest.mark.parametrize("normals, free", [
    ([(0, 1, 0), (0, 0, -1)], (1, 0, 0)),  # a wall meeting a ceiling: free along their edge
    ([(0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)], (1, 0, 0)),  # a corridor: free along it
])
def test_two_planes_and_a_corridor_leave_their_direction_free(normals, free):
    H, n = _planes(normals)
    _, vectors, constrained = constrained_directions(H, n, CAMERA, 1.5)
    assert (~constrained).sum() == 1
    cov = pose_covariance(H, chi2=0.1 * n, n=n, t=CAMERA, depth=1.5)
    assert abs(cov.weak_direction @ np.array(free)) > np.cos(np.radians(25))
    assert cov.sigma_m == pytest.approx(PRIOR_SIGMA_M, rel=0.05)  # nothing but the prior along it
    assert np.sqrt(np.array(free) @ cov.matrix[:3, :3] @ np.array(free)) > 10 * np.sqrt(
        np.linalg.eigvalsh(cov.matrix[:3, :3])[1])  # far above every other axis


def _depth_of_planes(planes, noisy: bool, seed: int = 0) -> tuple[np.ndarray, Intrinsics]:
    """A 320 x 240 depth image (camera frame: x right, y down, z ahead) of the nearest of the planes n . X = c in
    front of the camera, with a Kinect-like noise (1.2 mm + 1.9 mm (z - 0.4)^2) where `noisy`."""
    intr = Intrinsics(320, 240, 271.6, 271.6, 159.5, 119.5)
    v, u = np.mgrid[0:240, 0:320]
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u, dtype=float)], -1)
    depth = np.full((240, 320), np.inf)
    for normal, c in planes:
        along = rays @ np.asarray(normal, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(along * c > 0, c / along, np.inf)
        depth = np.minimum(depth, t)
    depth[~np.isfinite(depth) | (depth > 5.0)] = 0.0
    if noisy:
        sigma = 0.0012 + 0.0019 * (depth - 0.4) ** 2
        depth = np.where(depth > 0, depth + np.random.default_rng(seed).normal(size=depth.shape) * sigma, 0.0)
    return depth.astype(np.float32), intr


FLOOR, CEILING = ((0, 1, 0), 1.0), ((0, 1, 0), -1.1)  # (camera frame: y is down)
WALL_AHEAD, WALL_RIGHT = ((0, 0, 1), 3.0), ((1, 0, 0), 1.0)


@pytest.mark.parametrize("noisy", [False, True])
def test_the_view_itself_constrains_a_corner_with_a_floor_not_two_planes_or_a_wall(noisy):
    """information.view_information: what the frame's own surfaces could pin down once the map holds them. Depth
    noise must not fake a constraint (unaveraged normals gave 60 along two planes' edge)."""
    corner, intr = _depth_of_planes([FLOOR, WALL_AHEAD, WALL_RIGHT], noisy)
    assert view_information(corner, intr) > 2 * UNCONSTRAINED_BELOW
    for planes in ([WALL_AHEAD, CEILING], [WALL_AHEAD, WALL_RIGHT], [WALL_AHEAD]):
        depth, intr = _depth_of_planes(planes, noisy)
        assert view_information(depth, intr) < UNCONSTRAINED_BELOW, planes  # (noisy, the wall 3 m away: 4-19; exact: 0)
    assert view_information(np.zeros((240, 320), np.float32), intr) == 0.0  # no depth: nothing pinned down


def test_the_step_moves_only_along_constrained_directions_and_the_free_part_is_what_is_left():
    H, n = _planes([(0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)])
    change = np.array([0.05, 0.01, -0.02, 0.0, 0.0, 0.0])
    free = unconstrained_part(H, n, CAMERA, 1.5, change)
    np.testing.assert_allclose(free[:3], [0.05, 0.0, 0.0], atol=1e-9)  # the corridor's axis only
    b = -H @ change  # normal equations whose solution is `change`
    step = constrained_step(H, b, n, CAMERA, 1.5)
    np.testing.assert_allclose(step + free, change, atol=1e-9)


def test_the_covariance_grows_with_the_residuals_and_shrinks_with_the_information():
    H, n = _planes([(1, 0, 0), (0, 1, 0), (0, 0, 1)])
    base = pose_covariance(H, 0.1 * n, n, CAMERA, 1.5).sigma_m
    assert pose_covariance(H, 0.4 * n, n, CAMERA, 1.5).sigma_m == pytest.approx(2 * base, rel=0.05)
    assert pose_covariance(4 * H, 0.1 * n, n, CAMERA, 1.5).sigma_m == pytest.approx(base / 2, rel=0.05)
    # the point count is a speed setting: twice the points with the same per-point information change nothing
    assert pose_covariance(2 * H, 0.1 * 2 * n, 2 * n, CAMERA, 1.5).sigma_m == pytest.approx(base, rel=0.02)


def test_pose_quality_csv_and_summary_say_how_far_each_pose_can_be_trusted():
    from eslam_core.outputs.export import tracking_summary, tracking_table
    from eslam_core.trajectory import TrackedTrajectory

    traj = TrackedTrajectory()
    traj.record(0, 0.0, np.eye(4), 0.0, None, keyframe=True)
    wide = np.diag([0.1**2, 1e-6, 1e-6, 1e-8, 1e-8, 1e-8])
    traj.record(1, 0.1, np.eye(4), 0.5, None, False, 0.6, False, True, wide)
    traj.record(2, 0.2, np.eye(4), 0.5, None, False, 0.0, True, False, None)
    lines = [line.split(",") for line in tracking_table(traj).splitlines()]
    assert lines[0][:7] == ["timestamp", "quality", "lost", "degraded", "sigma_m", "sigma_deg", "cov_x_x"]
    assert len(lines[0]) == 6 + 21 and all(len(line) == len(lines[0]) for line in lines)
    assert lines[1][1:5] == ["1.000", "0", "0", ""] and lines[3][1:5] == ["0.000", "1", "0", ""]
    assert lines[2][3:5] == ["1", "0.10000"] and float(lines[2][6]) == pytest.approx(0.01)
    assert tracking_summary(traj) == {"frames_lost": 1, "frames_degraded": 1, "sigma_m_median": pytest.approx(0.1)}
