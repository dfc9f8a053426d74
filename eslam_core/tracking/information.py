"""How well a tracked pose is determined: the alignment's information matrix, its weakest direction and the pose
covariance (not part of the paper's method).

The SDF tracker's Gauss-Newton sums, over the frame's points, H = sum_i w_i J_i^T J_i for a left perturbation
(v, w) of the pose (x -> x + w x x + v); its residuals are unitless (each divided by its robust scale). Where the
view pins the pose down, H is large in every direction; a wall seen head-on gives no information along itself, a
ceiling meeting a wall none along their edge, a corridor none along its length, and there the solver's answer is
whatever its start was.

Covariance: s^2 (H / n)^-1 / EFFECTIVE_POINTS, with s^2 the residuals' weighted mean square. Not
s^2 H^-1: the n points share the map's error and the frame's (a map a few millimetres off moves all of them
together), so the pose is not n times better for n points; the tracker's point count is a speed setting, not a
certainty. EFFECTIVE_POINTS is the number of independent points that the errors measured on tracked frames are
worth. A prior of one frame's plausible motion keeps the covariance finite where nothing constrains a direction.

The covariance is given in the world frame in REP 103's order (x y z roll pitch yaw: the position and small turns
about the fixed world axes), as a nav_msgs/Odometry's pose covariance wants it: the position's perturbation is
v + w x t (the camera's own move), its turn w.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from eslam_core.camera import Intrinsics
from eslam_core.geometry import skew
from eslam_core.mapping.map_frame import depth_points_and_normals

# Independent points a frame's alignment is worth: set so that the position errors of tracked frames against the
# truth are the size of the predicted standard deviations. `fast`, lock-step, median of error / sqrt(trace of the
# position covariance): 0.36 on 120 frames of the synthetic room, 0.40 on ICL office kt0 (300), 2.57 on 7-Scenes
# RedKitchen (400), whose error is mostly the map's drift and its reference poses' own, which no single frame sees
# (README: "Degenerate views and the pose covariance").
EFFECTIVE_POINTS = 12.0
# A direction of the pose whose information per residual is below this is not constrained by the frame: the solver
# does not step along it and the covariance there is the prior's. Units: unitless residual^2 per m^2 of motion, a
# turn counted as the motion of a point at the median depth (an SDF residual per 1 cm Huber scale moved along its
# surface normal gives 10^4). Measured along each frame's weakest direction (`fast`, lock-step): 111-149 (5th-95th
# percentile) on the synthetic room, 112-1203 on ICL office kt0, 145-557 on 7-Scenes RedKitchen; below 15 where
# only a wall, two planes or a corridor are in view (datasets/degenerate.py). At 20, single frames at the start of
# such a view were 2.1-2.7 cm off and not flagged.
UNCONSTRAINED_BELOW = 40.0
# A direction constrained, but weakly: information per residual below this. The odometry sees the same view, and
# its move along such a direction is no better than a guess that the tracker, finding the cost nearly flat there,
# keeps (quality.py: a pose that moved along it beyond the constant velocity is degraded). On the generated
# corridor's turn the information fell 88 -> 50 -> 45 over two frames while the odometry moved the camera 1.6 and
# 4.7 cm along the corridor (it crept 0.2 cm), and the tracker kept both moves. Real views lie mostly above it: the
# weakest direction's 1st percentile was 78-96 on ICL office kt0 (300 frames) and 89-105 on 7-Scenes RedKitchen
# (400), two runs each (`fast`, lock-step); at most 5 frames of a run below 80, none degraded.
WEAK_BELOW = 80.0
# One frame's plausible motion (standard deviation, metres; a turn as the motion of a point at the median depth):
# the prior that bounds a direction nothing constrains.
PRIOR_SIGMA_M = 0.10
# The depth is averaged over this many pixels square before its normals are taken (view_information): Kinect-like
# noise scatters raw normals enough to fake a constraint (the synthetic ceiling meeting a wall: 60 along their edge
# from raw normals, 3 from averaged ones; the generated flat's views 76-147 either way).
VIEW_SMOOTHING_PX = 5


@dataclass(frozen=True)
class PoseCovariance:
    """A tracked pose's uncertainty."""

    matrix: np.ndarray  # (6, 6) world frame, x y z roll pitch yaw (metres, radians)
    free: bool = False  # some direction is not constrained by the frame (its variance is the prior's)
    weakest: float = float("inf")  # information per residual along the least constrained direction

    @property
    def sigma_m(self) -> float:
        """The position's standard deviation along its worst-determined axis."""
        return float(np.sqrt(max(np.linalg.eigvalsh(self.matrix[:3, :3])[-1], 0.0)))

    @property
    def weak_direction(self) -> np.ndarray:
        """The unit world direction of that axis (its sign is arbitrary)."""
        return np.linalg.eigh(self.matrix[:3, :3])[1][:, -1]

    def rotated(self, R: np.ndarray) -> "PoseCovariance":
        """The covariance of the same pose seen from a frame turned by R (a submap's anchor: information.py's
        position moves and turns about fixed axes both turn with the frame)."""
        B = np.zeros((6, 6))
        B[:3, :3] = B[3:, 3:] = np.asarray(R, dtype=np.float64)
        return PoseCovariance(B @ self.matrix @ B.T, self.free, self.weakest)

    @property
    def sigma_deg(self) -> float:
        """The rotation's standard deviation about its worst-determined axis."""
        return float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(self.matrix[3:, 3:])[-1], 0.0))))


def _turn_scale(depth: float) -> np.ndarray:
    """D with (v_c, w) = D s: s counts a turn w as the motion d w of a point at the median depth d."""
    return np.diag([1.0, 1.0, 1.0] + [1.0 / max(depth, 1e-3)] * 3)


def _to_solver(t: np.ndarray, depth: float) -> np.ndarray:
    """T with (v, w) = T s: s = (v_c, d w) are the pose change in metres of point motion, the turn w about the
    camera centre t (v_c = v + w x t, the camera's own move) and counted at the median depth d."""
    T = np.eye(6)
    T[:3, 3:] = skew(t)  # v = v_c - w x t = v_c + [t]x w
    return T @ _turn_scale(depth)


def constrained_directions(H: np.ndarray, n: int, t: np.ndarray, depth: float
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The eigenvalues (information per residual, ascending) and eigenvectors (columns, in the coordinates s of
    _to_solver) of the normal equations H of n residuals at a camera at t, and which of them the frame
    constrains."""
    T = _to_solver(t, depth)
    information, vectors = np.linalg.eigh(T.T @ np.asarray(H, dtype=np.float64) @ T / max(int(n), 1))
    return information, vectors, information >= UNCONSTRAINED_BELOW


def constrained_step(H: np.ndarray, b: np.ndarray, n: int, t: np.ndarray, depth: float) -> np.ndarray:
    """The Gauss-Newton step (v, w) solving H delta = -b in the constrained directions only; along the others the
    pose stays where it is (the solver would otherwise follow noise there, as far as it likes)."""
    information, vectors, constrained = constrained_directions(H, n, t, depth)
    T = _to_solver(t, depth)
    V = vectors[:, constrained]
    return -T @ V @ ((V.T @ T.T @ np.asarray(b, dtype=np.float64) / max(int(n), 1)) / information[constrained])


def unconstrained_part(H: np.ndarray, n: int, t: np.ndarray, depth: float, delta: np.ndarray) -> np.ndarray:
    """The part of a pose change (v, w) that lies in the directions the frame does not constrain (zero where it
    constrains every direction)."""
    _, vectors, constrained = constrained_directions(H, n, t, depth)
    T = _to_solver(t, depth)
    V = vectors[:, ~constrained]
    return T @ V @ (V.T @ np.linalg.solve(T, np.asarray(delta, dtype=np.float64)))


def pose_covariance(H: np.ndarray, chi2: float, n: int, t: np.ndarray, depth: float) -> PoseCovariance:
    """The covariance of a pose (camera at t) aligned with normal equations H (6x6, all residual terms), weighted
    squared residuals chi2 over n residuals, points at median depth `depth`."""
    n = max(int(n), 7)
    s2 = max(float(chi2) / (n - 6), 1e-6)
    information, vectors, constrained = constrained_directions(H, n, t, depth)
    variances = np.where(constrained, 1.0 / (information * EFFECTIVE_POINTS / s2 + PRIOR_SIGMA_M**-2),
                         PRIOR_SIGMA_M**2)
    # (v_c, w) = D s: the camera's move and its turn, which is what REP 103's pose covariance is of.
    D = _turn_scale(depth)
    covariance = D @ (vectors * variances) @ vectors.T @ D
    return PoseCovariance(0.5 * (covariance + covariance.T), not constrained.all(), float(information[0]))


def covariance_at(covariance: np.ndarray, lever: np.ndarray) -> np.ndarray:
    """The covariance (x y z roll pitch yaw, world frame) of a frame rigidly attached to the tracked camera at
    `lever` (world vector from the camera to it, e.g. the robot's base): its position also moves with the turn,
    by w x lever."""
    A = np.eye(6)
    A[:3, 3:] = -skew(lever)
    return A @ np.asarray(covariance, dtype=np.float64) @ A.T


def view_information(depth: np.ndarray, intr: Intrinsics) -> float:
    """Information per residual, along the least constrained direction, that the frame's own geometry gives: each
    point aligned to the plane of its own surface (point-to-plane, the residual per 1 cm, as the SDF tracker's), in
    the units of UNCONSTRAINED_BELOW. What the view could pin down once the map holds it, where the tracker's
    information is what the map holds of it: a view whose geometry leaves a direction free (a wall, two planes, a
    corridor) is low in both, a view into space the map has not settled yet only in the tracker's."""
    d = np.asarray(depth, dtype=np.float32)
    valid = (d > 0).astype(np.float32)
    k = (VIEW_SMOOTHING_PX, VIEW_SMOOTHING_PX)
    total, count = cv2.boxFilter(d, -1, k, normalize=False), cv2.boxFilter(valid, -1, k, normalize=False)
    smooth = np.where((count > 0.6 * VIEW_SMOOTHING_PX**2) & (d > 0), total / np.maximum(count, 1.0), 0.0)
    points, normals = depth_points_and_normals(smooth, intr)
    if len(points) < 50:
        return 0.0
    J = np.concatenate([normals, np.cross(points, normals)], axis=1) / 0.01
    information, _, _ = constrained_directions(J.T @ J, len(J), np.zeros(3), float(np.median(points[:, 2])))
    return float(information[0])
