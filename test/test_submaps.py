"""Submaps (submaps/atlas.py) on the synthetic long room, lock-step: the walk is mapped in several submaps that
track as one map does, each submap's mesh follows its anchor, and a checkpoint with several submaps is saved,
loaded and relocalized against."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from eslam_core.camera import Frame
from eslam_core.config import ConfigError, load_config
from eslam_core.datasets import open_dataset
from eslam_core.datasets.synthetic import generate_scene
from eslam_core.demo import mesh_scores
from eslam_core.map_file import read_checkpoint
from eslam_core.outputs.export import submap_mesh
from eslam_core.outputs.mesh import save_ply
from eslam_core.slam import CHECKPOINT_VERSION, SLAM
from eslam_core.tracking.map_check import MapCheck
from eslam_core.tracking.session import PoseCorrections

RADIUS_M = 1.0


@pytest.fixture(scope="module")
def long_room(tmp_path_factory):
    """The camera walks 3.7 m along a room twice as long as the embedded one, looking across it."""
    path = generate_scene(tmp_path_factory.mktemp("long") / "seq", n_frames=150, width=160, height=120, seed=1,
                          layout="long_room")
    return open_dataset(path, "tum")


@pytest.fixture(scope="module")
def mapped(long_room):
    """The walk with submaps (lock-step, `fast`)."""
    cfg = load_config("fast", {"scene": {"bound_margin": 0.3}, "submaps": {"radius_m": RADIUS_M}})
    slam = SLAM(cfg, long_room.intrinsics)
    for i in range(len(long_room)):
        f = long_room[i]
        slam.step(Frame(i, f.timestamp, f.rgb, f.depth, f.pose))
    return slam


def test_the_walk_is_mapped_in_submaps_that_track_as_one_map(mapped, long_room):
    slam = mapped
    atlas = slam.atlas
    assert len(atlas.submaps) >= 3  # 3.7 m at 1 m from each anchor
    truth = np.stack(long_room.gt_poses())
    poses = np.stack([slam.trajectory.pose(i) for i in range(len(long_room))])
    error = np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert np.sqrt(np.mean(error ** 2)) < 0.03  # a constant pose is metres off
    for sub in atlas.submaps[1:]:  # each anchored where the camera was when it began, with the world's axes
        assert np.allclose(sub.anchor[:3, :3], np.eye(3))
        assert np.allclose(sub.centre, 0.0, atol=1e-6)  # (its first keyframe's position, in its own frame)
        assert sum(atlas.owns(sub, kf.number) for kf in sub.keyframes) >= 2
    assert sum(not e.loop for e in atlas.graph.edges) == len(atlas.submaps) - 1  # one per submap begun
    assert np.allclose(atlas.centre(atlas.submaps[0]), poses[0][:3, 3], atol=1e-4)  # where the walk began
    for sub in atlas.submaps:  # each holds its keyframes within the radius of where it began
        for kf in (kf for kf in sub.keyframes if atlas.owns(sub, kf.number)):
            assert np.linalg.norm(kf.pose.double().numpy()[:3, 3] - sub.centre) < RADIUS_M + 0.05


def test_the_mesh_of_every_submap_lies_on_the_true_surface(mapped, long_room, tmp_path):
    from eslam_core.outputs.export import map_mesh

    slam = mapped
    path = save_ply(map_mesh(slam, 0.03), tmp_path / "mesh.ply")
    scores = mesh_scores(path, long_room.root / "mesh.ply", long_room, 0.06, n_points=60_000)
    assert scores.accuracy < 0.03 and scores.completion_ratio > 0.5


def test_a_submap_moved_rigidly_meshes_the_moved_surface(mapped):
    slam = mapped
    sub = slam.atlas.submaps[1]
    before = submap_mesh(slam, sub, 0.04)
    moved = sub.anchor.copy()
    moved[:3, 3] += [0.3, -0.2, 0.1]
    anchor, sub.anchor = sub.anchor, moved
    try:
        after = submap_mesh(slam, sub, 0.04)
    finally:
        sub.anchor = anchor
    assert len(after.vertices) == len(before.vertices)
    assert np.allclose(after.vertices - before.vertices, [0.3, -0.2, 0.1], atol=1e-5)


def test_a_checkpoint_with_several_submaps_is_loaded_and_relocalized_against(mapped, long_room):
    slam = mapped
    state = slam.state_dict()
    loaded = SLAM.from_state_dict(state)
    assert len(loaded.atlas.submaps) == len(slam.atlas.submaps)
    for a, b in zip(loaded.atlas.submaps, slam.atlas.submaps):
        assert np.allclose(loaded.atlas.anchor(a), slam.atlas.anchor(b))
        assert len(a.keyframes) == len(b.keyframes)
    i = 60  # a view of the middle of the walk: a loaded map starts lost, and is found there
    result = None
    for k in range(3):
        g = long_room[i + k]
        result = loaded.step(Frame(1000 + k, 100.0 + k / 30, g.rgb, g.depth, g.pose))
    assert not result.lost
    assert np.linalg.norm(result.pose[:3, 3] - long_room[i + 2].pose[:3, 3]) < 0.05


def loop_check(atlas, shift_m: float, turn_deg: float = 0.0):
    """The newest submap's first keyframe as the first submap's first keyframe would place it: its tracked pose
    moved by `shift_m` along x and turned by `turn_deg` about the vertical (a loop, right or wrong)."""
    by, keyframe = atlas.submaps[0].keyframes[0].number, atlas.submaps[-1].keyframes[0].number
    tracked = atlas.keyframe_pose(keyframe)
    c, s = np.cos(np.radians(turn_deg)), np.sin(np.radians(turn_deg))
    placed = tracked.copy()
    placed[:3, :3] = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ tracked[:3, :3]
    placed[0, 3] += shift_m
    return MapCheck(keyframe, by, shift_m, turn_deg, disagrees=True, placed=placed)


def test_a_loop_between_submaps_moves_the_later_ones_rigidly_toward_it(mapped, tmp_path):
    slam = SLAM.from_state_dict(mapped.state_dict())
    atlas = slam.atlas
    check = loop_check(atlas, 0.04)
    anchors = [atlas.anchor(s).copy() for s in atlas.submaps]
    corrections = atlas.close_loop(check, frame=149)
    assert atlas.loops == 1
    closure = atlas.closures[0]  # reported in summary.json: when the place was revisited and the map corrected
    assert (closure.keyframe, closure.by, closure.corrected) == (check.keyframe, check.by, 149)
    assert closure.revisit == atlas.submaps[-1].keyframes[0].frame_index
    torch.save(slam.state_dict(), tmp_path / "checkpoint.pt")  # a checkpoint keeps the loops closed
    loaded = SLAM.from_state_dict(read_checkpoint(tmp_path / "checkpoint.pt", CHECKPOINT_VERSION)).atlas
    assert loaded.loops == 1 and loaded.closures == atlas.closures
    moved = [atlas.anchor(s)[0, 3] - a[0, 3] for s, a in zip(atlas.submaps, anchors)]
    assert moved[0] == 0.0  # the world's submap stays put
    assert 0.01 < moved[-1] <= 0.04 + 1e-6  # toward the loop, as far as the odometry's drift allows
    assert all(a <= b + 1e-9 for a, b in zip(moved, moved[1:]))  # the farther along the walk, the more
    last = atlas.submaps[-1]
    for kf in (kf for kf in last.keyframes if atlas.owns(last, kf.number)):  # a moved submap's own keyframes
        assert np.allclose(corrections[kf.number], atlas.anchor(last) @ kf.pose.double().numpy(), atol=1e-5)
    slam.tracking.apply(PoseCorrections(corrections, ()))
    kf = last.keyframes[0]  # the trajectory follows: the keyframe's own frame is where the correction put it
    assert np.allclose(slam.trajectory.pose(kf.frame_index), corrections[kf.number], atol=1e-5)


def test_a_wrong_loop_between_submaps_does_not_move_the_map(mapped):
    slam = SLAM.from_state_dict(mapped.state_dict())
    atlas = slam.atlas
    anchors = [atlas.anchor(s).copy() for s in atlas.submaps]
    assert atlas.close_loop(loop_check(atlas, 0.9, turn_deg=30.0)) == {}  # another place, 0.9 m away
    assert atlas.loops == 0 and atlas.closures == []
    for sub, before in zip(atlas.submaps, anchors):
        assert np.linalg.norm(atlas.anchor(sub)[:3, 3] - before[:3, 3]) < 0.01


def test_submaps_need_a_growing_map_and_lock_step():
    with pytest.raises(ConfigError, match="submaps.radius_m"):
        load_config("fast", {"submaps": {"radius_m": 2.0}, "scene": {"bound": [[0, 0, 0], [1, 1, 1]]}})
    with pytest.raises(ConfigError, match="submaps.radius_m"):
        load_config("fast", {"submaps": {"radius_m": 0.5}})
    from eslam_core.runtime import make_runtime
    from eslam_core.runtime.api import RuntimeSetupError
    from eslam_core.datasets.synthetic import default_intrinsics

    with pytest.raises(RuntimeSetupError, match="lock-step"):
        make_runtime(load_config("fast", {"submaps": {"radius_m": 2.0}}), default_intrinsics(160, 120), workers=2)
