"""Depth consistency score: exact poses on exact depth score 0, pose errors raise it, occlusions do not count."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.transform import Rotation

from eslam_core.camera import Intrinsics
from eslam_core.datasets.synthetic import build_room, default_intrinsics, handheld_trajectory, look_at
from eslam_core.mapping.consistency import (
    choose_pairs,
    keyframe_consistency,
    pair_consistency,
    sequence_consistency,
    warp_residuals,
)
from eslam_core.rendering.raycast import render_depth

INTR = default_intrinsics(160, 120)
NUMBERS = list(range(0, 150, 10))  # every 10th frame of a 5 s hand-held path


@pytest.fixture(scope="module")
def room_views():
    """Exact depth of the synthetic room along a hand-held path that turns back to where it started."""
    scene = build_room(0)
    poses = handheld_trajectory(150, seed=0)[NUMBERS]
    depths = [render_depth(scene.mesh, INTR, pose)[0] for pose in poses]
    pairs = choose_pairs(depths, poses, NUMBERS, INTR, near_frames=10, far_frames=60)
    return depths, poses, pairs


def perturbed(poses: np.ndarray, size: float, seed: int = 0) -> np.ndarray:
    """Each pose moved by a random rigid motion: `size` metres of translation and `size` radians of rotation."""
    rng = np.random.default_rng(seed)
    out = poses.copy()
    for k in range(len(out)):
        axis, direction = rng.normal(size=3), rng.normal(size=3)
        motion = np.eye(4)
        motion[:3, :3] = Rotation.from_rotvec(size * axis / np.linalg.norm(axis)).as_matrix()
        motion[:3, 3] = size * direction / np.linalg.norm(direction)
        out[k] = out[k] @ motion
    return out


def test_pairs_cover_near_frames_and_revisits(room_views):
    depths, poses, pairs = room_views
    kinds = {kind for _, _, kind in pairs}
    assert kinds == {"near", "far"}
    for k, m, kind in pairs:
        gap = NUMBERS[m] - NUMBERS[k]
        assert gap >= (10 if kind == "near" else 60)
    assert any(NUMBERS[m] - NUMBERS[k] >= 120 for k, m, _ in pairs)  # frames 4 s apart that see the same surface


def test_exact_poses_and_exact_depth_score_zero(room_views):
    depths, poses, pairs = room_views
    result = sequence_consistency(depths, poses, pairs, INTR, frame_numbers=NUMBERS, stride=2)
    assert result.compared > 50_000
    assert result.median_mm < 0.01  # float32 depth precision
    assert result.agree_fraction == 1.0
    assert all(p.median_mm < 0.01 for p in result.pairs)
    assert result.pairs[0].first == NUMBERS[pairs[0][0]]  # pairs are named by frame number


def test_score_grows_with_a_known_pose_perturbation(room_views):
    depths, poses, pairs = room_views
    medians, agreements = [], []
    for size in (0.0, 0.005, 0.01, 0.02, 0.04):
        result = sequence_consistency(depths, perturbed(poses, size), pairs, INTR, stride=2)
        medians.append(result.median_mm)
        agreements.append(result.agree_fraction)
    assert np.all(np.diff(medians) > 0) and np.all(np.diff(agreements) < 0)
    assert 2.0 < medians[1] < 10.0  # 5 mm and 5 mrad of error: a few mm of residual
    assert medians[-1] > 15.0 and agreements[-1] < 0.8  # 4 cm: many pixels disagree by more than 3 cm


def test_an_error_along_the_viewing_axis_cannot_hide_behind_the_surface(room_views):
    depths, poses, _ = room_views
    a, b = 0, 1
    backwards = poses[b].copy()
    backwards[:3, 3] -= 0.05 * poses[b][:3, 2]  # b believed 5 cm behind where it was
    # One way, a's surface lands behind b's measured one: most points look occluded and are dropped, and what
    # is left mostly agrees within 3 cm (one-way, the error would nearly vanish) ...
    forward, hidden = warp_residuals(depths[a], depths[b], np.linalg.solve(backwards, poses[a]), INTR, stride=2)
    assert hidden > 2 * len(forward) and np.mean(np.abs(forward) <= 0.03) > 0.9
    # ... the other way b's points land in front of a's surface, and count: the pair reports the error.
    pair, _ = pair_consistency(depths[a], depths[b], poses[a], backwards, INTR, stride=2)
    assert 30.0 < pair.median_mm < 70.0 and pair.agree_fraction < 0.5


def test_occluded_pixels_are_ignored():
    """A box 1.5 m in front of a wall 3 m away: the second camera, 0.5 m to the side, does not see the wall
    behind the box that the first camera sees. With exact poses those pixels must not count as errors."""
    wall = trimesh.creation.box(extents=(8.0, 6.0, 0.1), transform=trimesh.transformations.translation_matrix(
        [0.0, 0.0, 3.05]))
    box = trimesh.creation.box(extents=(0.6, 0.6, 0.6), transform=trimesh.transformations.translation_matrix(
        [0.0, 0.0, 1.5]))
    scene = trimesh.util.concatenate([wall, box])
    intr = Intrinsics(160, 120, 120.0, 120.0, 79.5, 59.5)
    pose_a = look_at([0.0, 0.0, 0.0], [0.0, 0.0, 3.0], up=(0.0, -1.0, 0.0))
    pose_b = look_at([0.5, 0.0, 0.0], [0.5, 0.0, 3.0], up=(0.0, -1.0, 0.0))
    depth_a, depth_b = render_depth(scene, intr, pose_a)[0], render_depth(scene, intr, pose_b)[0]

    residuals, hidden = warp_residuals(depth_a, depth_b, np.linalg.solve(pose_b, pose_a), intr, stride=1)
    assert hidden > 500  # wall pixels of a that the box hides from b
    assert np.abs(residuals).max() < 1e-4  # what was compared agrees exactly
    pair, _ = pair_consistency(depth_a, depth_b, pose_a, pose_b, intr, stride=1)
    assert pair.occluded > 1000 and pair.median_mm < 0.01 and pair.agree_fraction == 1.0

    # with b believed 3 cm nearer the wall than it was, the same pair disagrees by about those 3 cm
    moved = pose_b.copy()
    moved[:3, 3] += [0.0, 0.0, 0.03]
    assert 25.0 < pair_consistency(depth_a, depth_b, pose_a, moved, intr, stride=1)[0].median_mm < 35.0


def test_keyframe_consistency_for_the_runtime_health(room_views):
    depths, poses, _ = room_views
    raw = [torch.from_numpy(np.round(d * 5000.0).astype(np.int16)) for d in depths[:8]]  # keyframe store's int16
    exact = keyframe_consistency(raw, torch.from_numpy(poses[:8]).float(), INTR, depth_scale=5000.0)
    assert exact.pairs >= 2 and exact.compared > 1000
    assert exact.median_mm < 0.5 and exact.agree_fraction > 0.99  # 0.2 mm depth steps, float32 poses
    drifted = poses[:8].copy()
    drifted[-1] = perturbed(poses[-1:], 0.03)[0]
    bad = keyframe_consistency(raw, drifted, INTR, depth_scale=5000.0)
    assert bad.median_mm > 10.0 and bad.agree_fraction < exact.agree_fraction
    assert keyframe_consistency(depths[:1], poses[:1], INTR).pairs == 0
    with pytest.raises(ValueError, match="depth_scale"):
        keyframe_consistency(raw[:2], poses[:2], INTR)
