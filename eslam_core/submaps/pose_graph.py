"""The pose graph (not part of the paper's method): poses as nodes, measured relative poses as edges weighted by
their information, solved by gtsam.

Odometry edges (consecutive poses, from tracking) are trusted; loop edges (a place recognised again) may be wrong,
and one wrong loop must not bend the map. gtsam's graduated non-convexity (GNC, truncated least squares) weighs
every loop edge while it solves: an edge that disagrees with the rest beyond the chi-square bound of its six
degrees of freedom gets weight 0, as if it had not been added. The first node is held where it is (the world's
origin stays put).

Conventions, gtsam's: an edge (a, b, T_ab) measures the pose of b in a's frame, T_ab = inv(T_a) T_b; its information
is over b's right perturbation T_b Exp(xi), xi = (rotation, translation), both in b's own frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

# The probability under which a correct loop edge's error stays within the inlier bound (the chi-square quantile
# of 6 degrees of freedom: 16.8 at 0.99).
LOOP_INLIER_PROBABILITY = 0.99
# Holds the first node: a standard deviation far below any tracked pose's (metres and radians).
ANCHOR_SIGMA = 1e-6


@dataclass(frozen=True)
class Edge:
    a: int
    b: int
    T_ab: np.ndarray  # (4, 4) the pose of b in a's frame
    information: np.ndarray  # (6, 6) over b's right perturbation (rotation, translation)
    loop: bool


@dataclass(frozen=True)
class Solution:
    poses: dict  # node -> (4, 4) float64 world pose
    rejected: tuple  # the loop edges given weight 0 (indices into PoseGraph.edges)


def body_information(covariance: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """The information of a pose over its right perturbation, from its covariance in the world frame in REP 103's
    order (x y z roll pitch yaw: the camera position's move and small turns about the world axes, as
    tracking/information.py gives it). A turn w about the world axes is R^T w about the pose's own axes; a position
    move d is R^T d along them (gtsam's retraction moves the position by R v)."""
    R = np.asarray(pose, dtype=np.float64)[:3, :3]
    to_body = np.zeros((6, 6))
    to_body[:3, 3:] = R.T  # rotation first in gtsam's order
    to_body[3:, :3] = R.T
    body = to_body @ np.asarray(covariance, dtype=np.float64) @ to_body.T
    return np.linalg.inv(0.5 * (body + body.T))


def _pose3(T: np.ndarray) -> gtsam.Pose3:
    return gtsam.Pose3(np.asarray(T, dtype=np.float64))


class PoseGraph:
    def __init__(self):
        self.initial: dict[int, np.ndarray] = {}
        self.edges: list[Edge] = []

    def add_node(self, key: int, pose: np.ndarray) -> None:
        """A node and its current estimate (the solver's start)."""
        if key in self.initial:
            raise ValueError(f"pose graph: node {key} exists already")
        self.initial[key] = np.array(pose, dtype=np.float64)

    def add_edge(self, a: int, b: int, T_ab: np.ndarray, information: np.ndarray, loop: bool) -> None:
        for key in (a, b):
            if key not in self.initial:
                raise ValueError(f"pose graph: edge to node {key}, which was never added")
        information = np.asarray(information, dtype=np.float64)
        if information.shape != (6, 6) or not np.all(np.isfinite(information)):
            raise ValueError(f"pose graph: edge {a} -> {b} needs a finite 6 x 6 information matrix")
        self.edges.append(Edge(a, b, np.array(T_ab, dtype=np.float64), information, loop))

    def _factors(self) -> tuple[gtsam.NonlinearFactorGraph, list[int]]:
        """The graph, and the indices of its trusted factors (the anchor's prior and every odometry edge)."""
        graph = gtsam.NonlinearFactorGraph()
        first = next(iter(self.initial))
        graph.add(gtsam.PriorFactorPose3(first, _pose3(self.initial[first]),
                                         gtsam.noiseModel.Isotropic.Sigma(6, ANCHOR_SIGMA)))
        trusted = [0]
        for e in self.edges:
            if not e.loop:
                trusted.append(graph.size())
            graph.add(gtsam.BetweenFactorPose3(e.a, e.b, _pose3(e.T_ab),
                                               gtsam.noiseModel.Gaussian.Information(e.information)))
        return graph, trusted

    def solve(self) -> Solution:
        """Every node's pose, agreeing best with the trusted edges and the loop edges that fit them."""
        if not self.initial:
            return Solution({}, ())
        graph, trusted = self._factors()
        values = gtsam.Values()
        for key, pose in self.initial.items():
            values.insert(key, _pose3(pose))
        if len(trusted) == graph.size():  # no loop edge: nothing to weigh
            result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
            rejected: tuple = ()
        else:
            params = gtsam.GncLMParams()
            params.setKnownInliers(trusted)
            optimizer = gtsam.GncLMOptimizer(graph, values, params)
            optimizer.setInlierCostThresholdsAtProbability(LOOP_INLIER_PROBABILITY)
            result = optimizer.optimize()
            weights = np.asarray(optimizer.getWeights())
            # factor i + 1 is edge i (factor 0 is the anchor's prior)
            rejected = tuple(i for i, e in enumerate(self.edges) if e.loop and weights[i + 1] < 0.5)
        return Solution({key: result.atPose3(key).matrix() for key in self.initial}, rejected)
