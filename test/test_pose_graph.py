"""The pose graph: a loop closed on a square path removes the drift; a wrong loop does not bend the map."""
from __future__ import annotations

import numpy as np
import pytest

from eslam_core.geometry import relative_motion, rotvec_to_matrix
from eslam_core.submaps.pose_graph import PoseGraph, body_information

SIDE_STEPS = 10  # poses per side of the square
STEP_M = 0.4


def square_path() -> list[np.ndarray]:
    """A camera walking a 4 m square and turning 90 degrees at each corner, back at its start."""
    poses, T = [], np.eye(4)
    for side in range(4):
        for _ in range(SIDE_STEPS):
            poses.append(T.copy())
            step = np.eye(4)
            step[0, 3] = STEP_M
            T = T @ step
        turn = np.eye(4)
        turn[:3, :3] = rotvec_to_matrix([0.0, 0.0, np.pi / 2])
        T = T @ turn
    return poses


def drifted(truth: list[np.ndarray], yaw_bias: float, rng: np.random.Generator) -> list[np.ndarray]:
    """Relative motions with a yaw bias and noise (the drift of odometry)."""
    out = []
    for a, b in zip(truth, truth[1:]):
        noise = np.eye(4)
        noise[:3, :3] = rotvec_to_matrix([0.0, 0.0, yaw_bias] + rng.normal(0, 0.001, 3))
        noise[:3, 3] = rng.normal(0, 0.002, 3)
        out.append(relative_motion(a, b) @ noise)
    return out


# The odometry's stated uncertainty per step: its yaw bias (YAW_BIAS) adds up to about twice the accumulated sigma
# around the square, as a calibrated covariance allows.
SIGMA_M, SIGMA_RAD, YAW_BIAS = 0.01, 0.01, 0.003


def odometry_graph(truth, motions, sigma_m=SIGMA_M, sigma_rad=SIGMA_RAD) -> tuple[PoseGraph, list[np.ndarray]]:
    info = np.diag([sigma_rad**-2] * 3 + [sigma_m**-2] * 3)
    g, T, estimate = PoseGraph(), truth[0].copy(), [truth[0].copy()]
    g.add_node(0, T)
    for i, M in enumerate(motions):
        T = T @ M
        estimate.append(T.copy())
        g.add_node(i + 1, T)
        g.add_edge(i, i + 1, M, info, loop=False)
    return g, estimate


def position_errors(poses: dict | list, truth: list[np.ndarray]) -> np.ndarray:
    items = poses.items() if isinstance(poses, dict) else enumerate(poses)
    return np.array([np.linalg.norm(T[:3, 3] - truth[k][:3, 3]) for k, T in items])


def closing_loop(truth) -> tuple:
    """The last pose seen again from the first: the true relative pose, measured to 1 cm / 0.5 degree."""
    n = len(truth) - 1
    info = np.diag([0.01**-2] * 3 + [0.01**-2] * 3)
    return 0, n, relative_motion(truth[0], truth[n]), info


def test_a_loop_closed_on_a_square_path_removes_the_drift():
    truth = square_path()
    g, estimate = odometry_graph(truth, drifted(truth, YAW_BIAS, np.random.default_rng(0)))
    before = position_errors(estimate, truth)
    assert before.max() > 0.2  # the drift is real: the end is tens of centimetres off
    g.add_edge(*closing_loop(truth), loop=True)
    solution = g.solve()
    after = position_errors(solution.poses, truth)
    assert solution.rejected == ()
    assert after.max() < before.max() / 3
    assert np.sqrt(np.mean(after**2)) < 0.05
    assert after[-1] < 0.03  # the end is back where it began
    assert np.allclose(solution.poses[0], truth[0], atol=1e-6)  # the first node stays put


def test_a_wrong_loop_does_not_move_the_map():
    truth = square_path()
    g, _ = odometry_graph(truth, drifted(truth, YAW_BIAS, np.random.default_rng(1)))
    g.add_edge(*closing_loop(truth), loop=True)
    right = g.solve().poses
    wrong = np.eye(4)
    wrong[:3, 3] = [0.8, -0.5, 0.0]  # a place mistaken for another 1 m away
    g.add_edge(10, 30, relative_motion(truth[10], truth[30]) @ wrong, np.diag([0.01**-2] * 6), loop=True)
    solution = g.solve()
    assert solution.rejected == (len(g.edges) - 1,)
    moved = [np.linalg.norm(solution.poses[k][:3, 3] - right[k][:3, 3]) for k in right]
    assert max(moved) < 0.01


def test_without_loops_the_graph_keeps_the_odometry():
    truth = square_path()
    g, estimate = odometry_graph(truth, drifted(truth, YAW_BIAS, np.random.default_rng(2)))
    solution = g.solve()
    assert max(np.abs(solution.poses[k] - estimate[k]).max() for k in range(len(estimate))) < 1e-6


def test_body_information_turns_a_world_covariance_into_the_poses_own_axes():
    pose = np.eye(4)
    pose[:3, :3] = rotvec_to_matrix([0.0, 0.0, np.pi / 2])  # the camera's x axis along the world's y
    cov = np.diag([1e-6, 1e-2, 1e-6, 1e-8, 1e-8, 1e-8])  # uncertain along world y only
    info = body_information(cov, pose)
    cov_body = np.linalg.inv(info)
    assert cov_body[3, 3] == pytest.approx(1e-2)  # the body's x (translation after rotation in gtsam's order)
    assert cov_body[4, 4] == pytest.approx(1e-6)


def test_an_edge_to_an_unknown_node_or_without_information_is_refused():
    g = PoseGraph()
    g.add_node(0, np.eye(4))
    with pytest.raises(ValueError, match="never added"):
        g.add_edge(0, 1, np.eye(4), np.eye(6), loop=False)
    g.add_node(1, np.eye(4))
    with pytest.raises(ValueError, match="information"):
        g.add_edge(0, 1, np.eye(4), np.full((6, 6), np.nan), loop=False)
    with pytest.raises(ValueError, match="exists"):
        g.add_node(1, np.eye(4))
