"""The map frame: the first camera's, turned so that the scene's walls and floor lie parallel to the feature planes.

ESLAM's feature planes are axis-aligned (xy, xz, yz). A wall parallel to one of them is a few cells of one plane and
a constant along the third axis; the same wall at 30 degrees cuts across every plane's cells, and the planes must
learn it as a staircase. Data sets hide this: their world frames are squared with the room (ICL-NUIM, Replica,
ScanNet) and runs start at the ground-truth pose. A camera on a robot starts at whatever angle it is held, and its
first frame is the map frame. Measured (`python bench/map_frame.py`, `live`, two processes, session 23): ICL office
frames 1-299, whose first camera is squared with the room: 0.23 cm; the same frames with the first frame turned 30
degrees about two random axes: 1.06 and 1.17 cm. 7-Scenes RedKitchen, 400 frames: from the first camera's frame
3.38 cm, squared as below 2.68 cm, from the data set's reference pose 2.82 cm.

The turn is the smallest rotation of the first camera's frame that makes the scene's two most common orthogonal
surface directions (a Manhattan frame: floor and a wall, or two walls) coordinate axes. Surface directions are the
normals of the first depth image; without one dominant direction (a view of clutter) the frame is left as it is,
and without a second one only the first is squared up.
"""
from __future__ import annotations

import itertools
from typing import Optional

import numpy as np

from eslam_core.camera import Intrinsics

TOLERANCE_DEG = 10.0  # a normal within this angle of a direction belongs to it (Kinect normals scatter by a few)
MIN_FIRST = 0.10  # fraction of the normals the dominant direction must hold to be trusted
MIN_SECOND = 0.02  # ... and the second one (7-Scenes RedKitchen frame 0: 0.27 and 0.05)
CANDIDATES = 300  # normals tried as the dominant direction
# Normals that vote for the candidates: every normal of a 640x480 frame voting took 0.15 s of the first frame, and a
# live tracker that late skipped the 5 frames waiting behind it (a sample's vote picks the same direction; its
# members are then taken from all the normals).
VOTERS = 3000


def depth_normals(depth: np.ndarray, intr: Intrinsics, step: int = 4) -> np.ndarray:
    """Unit surface normals (N, 3), camera frame, sign arbitrary (see `depth_points_and_normals`)."""
    return depth_points_and_normals(depth, intr, step)[1]


def depth_points_and_normals(depth: np.ndarray, intr: Intrinsics, step: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) and their unit surface normals (N, 3), camera frame, the normals' sign arbitrary: on a grid of
    every `step`-th pixel, the cross product of the back-projected neighbours `step` pixels left/right and
    above/below. Pixels whose neighbours are missing or across a depth edge (more than 5 % + 1 cm apart) give
    none."""
    d = np.asarray(depth, dtype=np.float64)
    height, width = d.shape
    rows, cols = np.arange(step, height - step, step), np.arange(step, width - step, step)
    r, c = np.meshgrid(rows, cols, indexing="ij")

    def point(rr: np.ndarray, cc: np.ndarray) -> np.ndarray:  # back-projected pixels (only those needed)
        z = d[rr, cc]
        return np.stack([(cc - intr.cx) / intr.fx * z, (rr - intr.cy) / intr.fy * z, z], axis=-1)

    z = d[r, c]
    valid = z > 0
    for rr, cc in [(r, c - step), (r, c + step), (r - step, c), (r + step, c)]:
        valid &= (d[rr, cc] > 0) & (np.abs(d[rr, cc] - z) < 0.05 * z + 0.01)
    across = point(r, c + step) - point(r, c - step)
    down = point(r + step, c) - point(r - step, c)
    normals = np.cross(across, down)[valid]
    length = np.linalg.norm(normals, axis=1)
    return point(r, c)[valid][length > 0], normals[length > 0] / length[length > 0, None]


def dominant_direction(normals: np.ndarray, tolerance_deg: float = TOLERANCE_DEG,
                       seed: int = 0) -> tuple[np.ndarray, float]:
    """The direction (unit, sign arbitrary) that most normals lie within `tolerance_deg` of, either way round, and
    the fraction of them that do. The best of `CANDIDATES` normals (by the votes of up to VOTERS of them), refined as
    the principal axis of its members."""
    if len(normals) == 0:
        return np.array([0.0, 0.0, 1.0]), 0.0
    cos_t = np.cos(np.radians(tolerance_deg))
    rng = np.random.default_rng(seed)
    candidates = normals[rng.choice(len(normals), min(CANDIDATES, len(normals)), replace=False)]
    voters = normals[rng.choice(len(normals), VOTERS, replace=False)] if len(normals) > VOTERS else normals
    votes = (np.abs(voters @ candidates.T) > cos_t).sum(axis=0)
    members = normals[np.abs(normals @ candidates[np.argmax(votes)]) > cos_t]
    _, vectors = np.linalg.eigh(members.T @ members)
    direction = vectors[:, -1]
    return direction, float((np.abs(normals @ direction) > cos_t).mean())


def surface_axes(normals: np.ndarray, tolerance_deg: float = TOLERANCE_DEG) -> Optional[np.ndarray]:
    """Three orthonormal directions (columns, camera frame, right-handed) squared with the scene's surfaces, or None
    when no direction holds `MIN_FIRST` of the normals. Without a second direction orthogonal to the first that
    holds `MIN_SECOND` of them, the second is the camera axis most orthogonal to the first (only the first is
    squared up)."""
    first, share = dominant_direction(normals, tolerance_deg)
    if share < MIN_FIRST:
        return None
    across = normals[np.abs(normals @ first) < np.sin(np.radians(tolerance_deg))]
    second, share = dominant_direction(across, tolerance_deg)
    if share * len(across) < MIN_SECOND * len(normals):
        second = np.eye(3)[np.argmin(np.abs(first))]
    second = second - first * (first @ second)
    second /= np.linalg.norm(second)
    return np.stack([first, second, np.cross(first, second)], axis=1)


def squaring_rotation(axes: np.ndarray) -> np.ndarray:
    """The camera-to-map rotation closest to identity that turns each of `axes` (columns) into a coordinate axis:
    of the 24 signed permutations P with det(P A^T) = 1, the one whose P A^T has the largest trace."""
    best, best_trace = np.eye(3), -np.inf
    for order in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            permutation = np.zeros((3, 3))
            permutation[list(order), range(3)] = signs
            rotation = permutation @ axes.T
            if np.linalg.det(rotation) > 0 and np.trace(rotation) > best_trace:
                best, best_trace = rotation, np.trace(rotation)
    return best


def squared_first_pose(depth: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """4x4 camera-to-map pose of the first frame: at the origin, turned so that its view's dominant surfaces are
    parallel to the feature planes (identity when none dominates)."""
    pose = np.eye(4)
    axes = surface_axes(depth_normals(depth, intr))
    if axes is not None:
        pose[:3, :3] = squaring_rotation(axes)
    return pose
