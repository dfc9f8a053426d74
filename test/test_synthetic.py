"""The embedded synthetic room: geometry, camera path, sensor model, TUM output and the cache."""
from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import trimesh
from PIL import Image
from scipy import ndimage

from eslam_core.camera import backproject
from eslam_core.rendering.raycast import render_depth
from eslam_core.datasets.synthetic import (
    PART_NAMES,
    WALL_PARTS,
    SensorModel,
    SyntheticSceneError,
    build_room,
    default_intrinsics,
    depth_noise_sigma,
    ensure_scene,
    frame_rng,
    generate_scene,
    handheld_trajectory,
    look_at,
    quaternion_to_rotation,
    render_frame,
    rotation_to_quaternion,
    write_tum_sequence,
)

IDEAL = SensorModel.ideal()


@pytest.fixture(scope="module")
def scene():
    return build_room(seed=0)


def test_room_is_one_closed_mesh_of_labelled_parts(scene):
    mesh = scene.mesh
    assert 1000 < len(mesh.faces) < 5000
    assert mesh.is_watertight
    np.testing.assert_allclose(scene.bound, [[-2.0, -1.5, 0.0], [2.0, 1.5, 2.6]])
    np.testing.assert_allclose(mesh.bounds, scene.bound, atol=1e-9)
    # every part but the light panels of the degenerate views (datasets/degenerate.py)
    assert set(np.unique(scene.part_ids)) == set(range(len(PART_NAMES))) - {PART_NAMES.index("lights")}
    np.testing.assert_array_equal(mesh.face_attributes["part"], scene.part_ids)
    # no face is a large sliver: big quads were subdivided
    edges = np.linalg.norm(np.diff(mesh.triangles[:, [0, 1, 2, 0]], axis=1), axis=2)
    assert edges.max() < 0.45
    # walls lie on the bound; all furniture stays below the camera's 1.2 m
    west = mesh.triangles[scene.part_mask(np.arange(len(mesh.faces)), "wall_west")]
    np.testing.assert_allclose(west[..., 0], -2.0, atol=1e-12)
    furniture = ~scene.part_mask(np.arange(len(mesh.faces)), "floor", "ceiling", "painting", *WALL_PARTS)
    assert mesh.triangles[furniture][..., 2].max() < 1.1


def test_ideal_depth_back_projects_onto_the_mesh(scene):
    intr = default_intrinsics(64, 48)
    rng = np.random.default_rng(3)
    for pose in handheld_trajectory(300, seed=1)[::100]:
        _, depth = render_frame(scene, intr, pose, frame_rng(0, 0), IDEAL)
        assert (depth > 0).mean() >= 0.9  # the room is seen (in fact every ray hits the closed room)
        points = backproject(depth, intr, pose)
        sample = points[rng.choice(len(points), 300, replace=False)]
        _, distance, _ = trimesh.proximity.closest_point(scene.mesh, sample)
        assert distance.max() < 1e-3


def test_handheld_trajectory_moves_like_a_walking_person():
    fps = 30.0
    poses = handheld_trajectory(900, fps=fps, seed=0, speed=0.25)
    assert poses.shape == (900, 4, 4)
    rot, pos = poses[:, :3, :3], poses[:, :3, 3]
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-9)
    np.testing.assert_array_equal(poses[:, 3], np.broadcast_to([0, 0, 0, 1], (900, 4)))

    step = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    assert 0.001 < step.min() and step.max() < 0.03
    assert step.mean() * fps == pytest.approx(0.25, rel=0.1)
    relative = rot[:-1].transpose(0, 2, 1) @ rot[1:]
    turn_deg = np.degrees(np.arccos(np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert turn_deg.max() < 2.0

    # free space: >= 0.5 m from every wall, hand height
    assert np.all(np.abs(pos[:, 0]) <= 1.5) and np.all(np.abs(pos[:, 1]) <= 1.0)
    assert pos[:, 2].min() >= 1.2 and pos[:, 2].max() <= 1.7
    # small roll: the camera's x axis stays within a few degrees of horizontal
    roll_deg = np.degrees(np.arcsin(np.abs(rot[:, 2, 0])))
    assert roll_deg.max() < 6.0 and roll_deg.max() > 0.5

    np.testing.assert_array_equal(poses, handheld_trajectory(900, fps=fps, seed=0, speed=0.25))
    assert np.abs(handheld_trajectory(900, seed=1)[:, :3, 3] - pos).max() > 0.1
    slow = np.linalg.norm(np.diff(handheld_trajectory(300, seed=0, speed=0.1)[:, :3, 3], axis=0), axis=1)
    assert slow.mean() * fps == pytest.approx(0.1, rel=0.1)


def test_camera_always_sees_plenty_of_room(scene):
    intr = default_intrinsics(40, 30)
    for seed in (0, 1):
        for pose in handheld_trajectory(1800, seed=seed)[::60]:
            depth, _ = render_depth(scene.mesh, intr, pose)
            assert (depth > 0).all()
            assert depth.min() > 0.4  # never pressed against a surface
            assert np.median(depth) > 1.0


def _view_of_east_wall(scene, distance: float, sensor: SensorModel, seed: int = 0):
    intr = default_intrinsics(96, 72)
    pose = look_at([2.0 - distance, 0.0, 1.8], [2.0, 0.0, 1.8])
    _, ideal = render_frame(scene, intr, pose, frame_rng(seed, 0), IDEAL)
    _, measured = render_frame(scene, intr, pose, frame_rng(seed, 0), sensor)
    _, faces = render_depth(scene.mesh, intr, pose)
    on_wall = scene.part_mask(faces, "wall_east") & (np.abs(ideal - distance) < 0.1) & (measured > 0)
    return ideal, measured, on_wall


def test_depth_noise_grows_with_distance_like_a_kinect(scene):
    stds = {}
    for distance in (1.0, 3.0):
        kinect_sigma = 0.0012 + 0.0019 * (distance - 0.4) ** 2
        assert depth_noise_sigma(distance, SensorModel()) == pytest.approx(kinect_sigma)
        ideal, measured, on_wall = _view_of_east_wall(scene, distance, SensorModel())
        assert on_wall.sum() > 1000
        error = (measured - ideal)[on_wall]
        assert abs(error.mean()) < 0.1 * kinect_sigma  # unbiased
        stds[distance] = error.std()
        assert stds[distance] == pytest.approx(kinect_sigma, rel=0.15)
    assert stds[3.0] > 4.0 * stds[1.0]
    # depth is stored at 1/5000 m
    _, measured, _ = _view_of_east_wall(scene, 1.0, SensorModel())
    steps = measured.astype(np.float64) * 5000.0
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-3)


def test_sensor_loses_depth_at_edges_on_the_lamp_and_at_random(scene):
    intr = default_intrinsics(96, 72)
    edge_pixels = flat_pixels = 0
    edge_missing = flat_missing = 0.0
    for i, pose in enumerate(handheld_trajectory(600, seed=0)[::150]):
        _, ideal = render_frame(scene, intr, pose, frame_rng(0, i), IDEAL)
        _, measured = render_frame(scene, intr, pose, frame_rng(0, i), SensorModel())
        spread = ndimage.maximum_filter(ideal, 3) - ndimage.minimum_filter(ideal, 3)
        edge, flat = spread > 0.3, spread < 0.02
        edge_pixels += edge.sum()
        flat_pixels += flat.sum()
        edge_missing += (measured[edge] == 0).sum()
        flat_missing += (measured[flat] == 0).sum()
    assert edge_pixels > 50
    assert edge_missing / edge_pixels > 0.95
    assert flat_missing / flat_pixels < 0.05

    # the dark metal lamp: most of its depth is missing
    pose = look_at([0.6, -0.4, 1.3], [1.65, -1.15, 0.85])
    _, measured = render_frame(scene, intr, pose, frame_rng(0, 0), SensorModel())
    _, faces = render_depth(scene.mesh, intr, pose)
    lamp = scene.part_mask(faces, "lamp")
    assert lamp.sum() > 50
    assert (measured[lamp] == 0).mean() > 0.75

    # random dropout alone removes its fraction; range and grazing limits remove exactly what they should
    pose = handheld_trajectory(1, seed=0)[0]
    _, measured = render_frame(scene, intr, pose, frame_rng(0, 0), replace(IDEAL, random_dropout=0.1))
    assert (measured == 0).mean() == pytest.approx(0.1, abs=0.02)
    _, ideal = render_frame(scene, intr, pose, frame_rng(0, 0), IDEAL)
    limited = replace(IDEAL, max_range_m=2.0)
    _, measured = render_frame(scene, intr, pose, frame_rng(0, 0), limited)
    np.testing.assert_array_equal(measured > 0, ideal <= 2.0)


def test_images_are_textured_and_seeded(scene):
    intr = default_intrinsics(64, 48)
    pose = look_at([0.0, 0.0, 1.6], [-2.0, 0.2, 1.6])  # facing the striped west wall
    rgb, depth = render_frame(scene, intr, pose, frame_rng(0, 0), IDEAL)
    _, faces = render_depth(scene.mesh, intr, pose)
    wall = scene.part_mask(faces, "wall_west")
    assert wall.mean() > 0.5
    grey = rgb.astype(np.float64).mean(axis=2)
    assert rgb[wall].std(axis=0).mean() > 15.0  # grey levels per channel: stripes and grain, not a flat colour
    assert grey[wall].std() > 15.0  # also in brightness, not only in hue
    # neighbouring pixels differ: there is high-frequency texture for photometric tracking
    assert np.abs(np.diff(grey, axis=1))[wall[:, 1:] & wall[:, :-1]].mean() > 3.0

    # the seed changes the textures, not the geometry; the same seed gives the same images
    other = build_room(seed=5)
    rgb_other, depth_other = render_frame(other, intr, pose, frame_rng(0, 0), IDEAL)
    np.testing.assert_array_equal(depth, depth_other)
    assert np.abs(rgb.astype(int) - rgb_other.astype(int)).mean() > 5.0
    np.testing.assert_array_equal(rgb, render_frame(build_room(seed=0), intr, pose, frame_rng(0, 0), IDEAL)[0])

    colours = scene.vertex_colors()
    assert colours.shape == (len(scene.mesh.vertices), 4) and colours.dtype == np.uint8
    albedo = scene.albedo(scene.mesh.triangles_center, np.arange(len(scene.mesh.faces)))
    assert albedo.min() >= 0.0 and albedo.max() <= 1.0
    lamp = scene.part_mask(np.arange(len(scene.mesh.faces)), "lamp")
    assert albedo[lamp].mean() < 0.2 < albedo[~lamp].mean()


def test_quaternions_round_trip_for_any_rotation():
    rng = np.random.default_rng(0)
    rotations = [quaternion_to_rotation(q) for q in rng.standard_normal((200, 4))]
    rotations += [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]), np.eye(3)]
    for rot in rotations:
        q = rotation_to_quaternion(rot)
        assert q[3] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
        np.testing.assert_allclose(quaternion_to_rotation(q), rot, atol=1e-12)
    # x-y-z-w order: 90 degrees about z
    np.testing.assert_allclose(rotation_to_quaternion([[0, -1, 0], [1, 0, 0], [0, 0, 1]]),
                               [0, 0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-12)  # fmt: skip


def _read_tum_list(path):
    rows = [line.split() for line in path.read_text().splitlines() if not line.startswith("#")]
    return [(float(r[0]), r[1:]) for r in rows]


def test_written_tum_folder_round_trips(scene, tmp_path):
    intr = default_intrinsics(64, 48)
    poses = handheld_trajectory(4, seed=2)
    out = write_tum_sequence(tmp_path / "seq", scene, poses, intr, IDEAL, seed=7)

    rgb_list, depth_list = _read_tum_list(out / "rgb.txt"), _read_tum_list(out / "depth.txt")
    assert (out / "rgb.txt").read_text().startswith("# ")
    assert [t for t, _ in rgb_list] == pytest.approx([i / 30.0 for i in range(4)], abs=1e-6)
    assert (out / "rgb.txt").read_text().splitlines()[4].split()[0] == "0.033333"
    for i, pose in enumerate(poses):
        rgb, depth = render_frame(scene, intr, pose, frame_rng(7, i), IDEAL)
        stored_rgb = np.asarray(Image.open(out / rgb_list[i][1][0]))
        stored_depth = np.asarray(Image.open(out / depth_list[i][1][0])).astype(np.float64) / 5000.0
        np.testing.assert_array_equal(stored_rgb, rgb)
        np.testing.assert_allclose(stored_depth, depth, atol=0.5 / 5000.0 + 1e-6)

    gt = _read_tum_list(out / "groundtruth.txt")
    assert len(gt) == 4
    for (timestamp, values), pose in zip(gt, poses):
        values = np.array(values, dtype=np.float64)
        np.testing.assert_allclose(values[:3], pose[:3, 3], atol=1e-6)
        np.testing.assert_allclose(quaternion_to_rotation(values[3:]), pose[:3, :3], atol=1e-6)

    camera = json.loads((out / "camera.json").read_text())
    assert camera == pytest.approx({"width": 64, "height": 48, "fx": intr.fx, "fy": intr.fy, "cx": 31.5, "cy": 23.5,
                                    "depth_scale": 5000.0})  # fmt: skip
    assert camera["fx"] == pytest.approx(0.5 * 64 / math.tan(math.radians(30.5)))
    mesh = trimesh.load(out / "mesh.ply", process=False)
    assert len(mesh.faces) == len(scene.mesh.faces)
    np.testing.assert_array_equal(mesh.visual.vertex_colors, scene.vertex_colors())
    info = json.loads((out / "scene.json").read_text())
    assert info["n_frames"] == 4 and info["seed"] == 7
    assert info["bound"] == scene.bound.tolist()
    assert SensorModel.from_json(info["sensor"]) == IDEAL

    # with the real sensor the stored depth is exactly the rendered (quantised) depth
    noisy = write_tum_sequence(tmp_path / "noisy", scene, poses[:1], intr, SensorModel(), seed=7)
    _, depth = render_frame(scene, intr, poses[0], frame_rng(7, 0), SensorModel())
    stored = np.asarray(Image.open(noisy / "depth" / "000000.png"))
    assert stored.dtype == np.uint16
    np.testing.assert_array_equal(stored, np.round(depth.astype(np.float64) * 5000.0).astype(np.uint16))


def test_ensure_scene_generates_once_and_regenerates_on_change(tmp_path):
    kwargs = dict(n_frames=3, width=32, height=24, seed=0)
    first = ensure_scene(tmp_path, **kwargs)
    assert len(list((first / "rgb").iterdir())) == 3
    stamp = {p: p.stat().st_mtime_ns for p in first.rglob("*")}

    again = ensure_scene(tmp_path, **kwargs)
    assert again == first
    assert {p: p.stat().st_mtime_ns for p in again.rglob("*")} == stamp

    other = ensure_scene(tmp_path, **{**kwargs, "seed": 1})
    assert other != first and json.loads((other / "scene.json").read_text())["seed"] == 1
    assert ensure_scene(tmp_path, **kwargs, sensor=IDEAL) not in (first, other)

    # an interrupted generation: no scene.json (it is written last) -> regenerated in place; a temp folder left by
    # a dead process is removed; nothing half-written remains
    (first / "scene.json").unlink()
    (first / "rgb" / "000002.png").unlink()
    abandoned = tmp_path / f".{first.name}.partial-99999999-x"
    abandoned.mkdir()
    regenerated = ensure_scene(tmp_path, **kwargs)
    assert regenerated == first and (first / "rgb" / "000002.png").exists() and (first / "scene.json").exists()
    assert not abandoned.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_generate_scene_writes_the_default_layout(tmp_path):
    out = generate_scene(tmp_path / "demo", n_frames=2, width=32, height=24, seed=3)
    names = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    assert names == ["camera.json", "depth.txt", "depth/000000.png", "depth/000001.png", "groundtruth.txt",
                     "mesh.ply", "rgb.txt", "rgb/000000.png", "rgb/000001.png", "scene.json"]  # fmt: skip
    with pytest.raises(SyntheticSceneError, match="not an empty folder"):
        generate_scene(out, n_frames=2, width=32, height=24)


def test_bad_input_is_reported_clearly(scene, tmp_path):
    with pytest.raises(ValueError, match="random_dropout"):
        SensorModel(random_dropout=1.5)
    with pytest.raises(SyntheticSceneError, match="unknown parts"):
        SensorModel(shiny_parts=("chandelier",))
    with pytest.raises(SyntheticSceneError, match="regenerate"):
        SensorModel.from_json({**SensorModel().to_json(), "speckle": 1.0})
    with pytest.raises(SyntheticSceneError, match="n_frames"):
        handheld_trajectory(0)
    with pytest.raises(SyntheticSceneError, match="proper rotation"):
        render_frame(scene, default_intrinsics(16, 12), np.diag([1.0, 1.0, -1.0, 1.0]), frame_rng(0, 0))
    with pytest.raises(SyntheticSceneError, match="face -1"):
        scene.albedo(np.zeros((1, 3)), np.array([-1]))
    with pytest.raises(SyntheticSceneError, match="too small"):
        generate_scene(tmp_path / "tiny", width=4, height=4)
