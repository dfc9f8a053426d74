"""The large generated scenes of the submap benchmark: walks a camera can track (small motions between frames),
always in free space inside the scene, looking at surfaces, and coming back where the benchmark needs a loop."""
from __future__ import annotations

import numpy as np
import pytest

from eslam_core.datasets.large_scenes import LAYOUTS, SCENES, generate_large_scene, walk
from eslam_core.datasets.synthetic import SyntheticSceneError, default_intrinsics, frame_rng, render_frame
from eslam_core.geometry import relative_motion, rotation_angle_deg


@pytest.fixture(scope="module", params=SCENES)
def scene(request):
    build, path = LAYOUTS[request.param]
    return request.param, build(0), walk(path())


def test_the_walk_moves_a_trackable_step_per_frame(scene):
    _, _, poses = scene
    steps = [relative_motion(a, b) for a, b in zip(poses, poses[1:])]
    assert max(np.linalg.norm(m[:3, 3]) for m in steps) < 0.04
    assert max(rotation_angle_deg(m[:3, :3]) for m in steps) < 3.0


def test_the_camera_stays_in_free_space_and_sees_surfaces(scene):
    name, built, poses = scene
    centres = poses[::25, :3, 3]
    assert np.all(centres > built.bound[0]) and np.all(centres < built.bound[1])
    _, distance, _ = built.mesh.nearest.on_surface(centres)
    assert distance.min() > 0.2, f"{name}: the camera passes {distance.min():.2f} m from a surface"
    intr = default_intrinsics(80, 60)
    for i in np.linspace(0, len(poses) - 1, 6).astype(int):
        _, depth = render_frame(built, intr, poses[i], frame_rng(0, i))
        assert (depth > 0).mean() > 0.6, f"{name}: frame {i} sees little within the sensor's range"


def test_the_walks_are_as_long_as_the_benchmark_says_and_come_back(scene):
    name, _, poses = scene
    length = float(np.sum(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)))
    start = poses[:40, :3, 3]
    back = np.linalg.norm(poses[-200:, None, :3, 3] - start[None], axis=2).min()
    if name == "corridor_loop":
        assert 28.0 < length < 40.0 and back < 0.3  # once round the ring, and on past the start
    if name == "flat":
        assert length > 25.0 and back < 0.3  # there and back
    if name == "two_storey":
        assert poses[-1, 2, 3] - poses[0, 2, 3] > 2.5  # it ends a storey up


def test_a_generated_folder_is_a_tum_sequence_with_its_mesh(tmp_path):
    from eslam_core.datasets import open_dataset

    folder = generate_large_scene(tmp_path / "loop", "corridor_loop", 64, 48, max_frames=3)
    ds = open_dataset(folder, "tum")
    assert len(ds) == 3 and (folder / "mesh.ply").is_file() and ds.gt_poses()[2] is not None
    with pytest.raises(SyntheticSceneError, match="unknown large scene"):
        generate_large_scene(tmp_path / "x", "castle")
