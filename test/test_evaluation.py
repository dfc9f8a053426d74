"""Evaluation metrics against known answers: ATE / RPE / alignment, accuracy / completion, ICP, depth L1, plots,
reports and the `eslam eval` command line. All data is generated here; meshes and trajectories are small."""
from __future__ import annotations

import json
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml
from scipy.spatial.transform import Rotation

from eslam_core.camera import Frame, Intrinsics
from eslam_core.evaluation import cli, plots
from eslam_core.evaluation.depth_l1 import depth_l1, look_at
from eslam_core.evaluation.reconstruction import (
    MeshError,
    check_mesh,
    icp_align,
    load_mesh,
    reconstruction_metrics,
    sample_surface,
)
from eslam_core.evaluation.report import (
    RunDirectoryError,
    compare_runs,
    evaluate_run,
    render_markdown,
    write_report_json,
)
from eslam_core.datasets.tum import read_tum, write_tum
from eslam_core.evaluation.trajectory_error import associate, ate, rpe, still_camera_ate, umeyama_alignment
from eslam_core.trajectory import Trajectory, TrajectoryError
from eslam_core.rendering.raycast import render_depth

# ---------------------------------------------------------------------------------------------------------------
# Helpers


def smooth_trajectory(n: int = 300, seed: int = 0) -> Trajectory:
    """A hand-held-like path: a 1.5 m wide loop with height changes, slowly turning camera."""
    t = np.linspace(0, 2 * np.pi, n)
    positions = np.stack([1.5 * np.cos(t), np.sin(2 * t), 0.3 * np.sin(3 * t)], 1)
    rng = np.random.default_rng(seed)
    angles = np.cumsum(rng.normal(0, 0.02, (n, 3)), axis=0)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(angles).as_matrix()
    poses[:, :3, 3] = positions
    return Trajectory(np.arange(n) / 30.0, poses)


def rigid(rotvec, translation) -> np.ndarray:
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    transform[:3, 3] = translation
    return transform


def square_plane(size: float = 1.0, z: float = 0.0, divisions: int = 4) -> trimesh.Trimesh:
    g = np.linspace(-size / 2, size / 2, divisions + 1)
    x, y = np.meshgrid(g, g, indexing="ij")
    vertices = np.stack([x, y, np.full_like(x, z)], -1).reshape(-1, 3)
    n = divisions + 1
    faces = []
    for i in range(divisions):
        for j in range(divisions):
            a, b, c, d = i * n + j, (i + 1) * n + j, i * n + j + 1, (i + 1) * n + j + 1
            faces += [[a, b, d], [a, d, c]]
    return trimesh.Trimesh(vertices, np.array(faces), process=False)


def room(extents=(4.0, 3.0, 2.5), subdivisions: int = 3) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=extents)
    for _ in range(subdivisions):
        mesh = mesh.subdivide()
    return mesh


def asymmetric_scene() -> trimesh.Trimesh:
    """Boxes of different sizes: every rigid motion changes the shape's position, so ICP has a unique answer."""
    parts = [
        trimesh.creation.box(extents=(2.0, 1.5, 1.0)),
        trimesh.creation.box(extents=(0.3, 0.5, 0.7), transform=rigid([0, 0, 0.3], [0.9, 0.5, 0.6])),
        trimesh.creation.box(extents=(0.6, 0.2, 0.4), transform=rigid([0.2, 0, 0], [-0.7, -0.6, 0.5])),
    ]
    return trimesh.util.concatenate(parts)


# ---------------------------------------------------------------------------------------------------------------
# Trajectory files and association


def test_tum_round_trip_and_quaternion_normalisation(tmp_path):
    traj = smooth_trajectory(50)
    path = write_tum(tmp_path / "traj.txt", traj)
    back = read_tum(path)
    np.testing.assert_allclose(back.timestamps, traj.timestamps, atol=1e-6)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-8)

    q = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_quat()  # x y z w
    (tmp_path / "scaled.txt").write_text(f"# comment\n\n1.0 1 2 3 {' '.join(str(2.5 * v) for v in q)}\n")
    scaled = read_tum(tmp_path / "scaled.txt")
    np.testing.assert_allclose(scaled.poses[0, :3, :3], Rotation.from_quat(q).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(scaled.poses[0, :3, 3], [1, 2, 3])


def test_read_tum_errors_name_file_line_and_timestamp(tmp_path):
    bad = tmp_path / "bad.txt"
    bad.write_text("0.0 0 0 0 0 0 0 1\n# comment\n0.1 0 0 0 0 0 1\n")
    with pytest.raises(TrajectoryError, match=r"bad.txt, line 3: expected 8 fields"):
        read_tum(bad)
    nan = tmp_path / "nan.txt"
    nan.write_text("0.0 0 0 0 0 0 0 1\n1.5 nan 0 0 0 0 0 1\n")
    with pytest.raises(TrajectoryError, match=r"nan.txt, line 2: pose at timestamp 1.5 is not finite"):
        read_tum(nan)
    with pytest.raises(TrajectoryError, match="not found"):
        read_tum(tmp_path / "missing.txt")
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[1, 0, 3] = np.inf
    with pytest.raises(TrajectoryError, match=r"timestamp 0\.25"):
        Trajectory(np.array([0.0, 0.25, 0.5]), poses)


def test_associate_matches_nearest_one_to_one_within_tolerance():
    gt = np.arange(0, 10, 1 / 30)
    est = np.concatenate([gt[::2] + 0.005, [100.0]])
    pairs = associate(est, gt, max_dt=0.02)
    np.testing.assert_array_equal(pairs[:, 0], np.arange(len(est) - 1))
    np.testing.assert_array_equal(pairs[:, 1], np.arange(0, len(gt), 2))
    # Two estimates near the same ground-truth stamp: the closer one gets it, the other its next-best partner.
    pairs = associate(np.array([1.001, 1.004]), np.array([1.0, 1.03]), max_dt=0.03)
    assert pairs.tolist() == [[0, 0], [1, 1]]
    pairs = associate(np.array([1.001, 1.004]), np.array([1.0]), max_dt=0.02)
    assert pairs.tolist() == [[0, 0]]
    with pytest.raises(TrajectoryError, match=r"no overlapping timestamps.*\[0\.005, 100\.000\].*\[0\.000, 9\.967\]"):
        associate(est, gt, max_dt=0.004)


# ---------------------------------------------------------------------------------------------------------------
# Alignment, ATE, RPE


def test_umeyama_recovers_known_transform_scale_and_avoids_reflections():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(100, 3))
    rotation = Rotation.from_rotvec([0.3, -1.2, 0.5]).as_matrix()
    dst = 1.0 * src @ rotation.T + [0.5, -2.0, 3.0]
    r, t, s = umeyama_alignment(src, dst)
    np.testing.assert_allclose(r, rotation, atol=1e-12)
    np.testing.assert_allclose(t, [0.5, -2.0, 3.0], atol=1e-12)
    assert s == 1.0
    r, t, s = umeyama_alignment(src, 2.5 * dst, with_scale=True)
    np.testing.assert_allclose([s, *t], [2.5, 1.25, -5.0, 7.5], atol=1e-10)
    # A mirrored copy: the best proper rotation is returned, never the reflection.
    r, _, _ = umeyama_alignment(src, src * [1, 1, -1])
    assert np.linalg.det(r) == pytest.approx(1.0)
    with pytest.raises(TrajectoryError, match="at least 3"):
        umeyama_alignment(src[:2], dst[:2])


def test_ate_is_zero_for_a_rigidly_moved_copy():
    gt = smooth_trajectory()
    motion = rigid([0.4, -0.3, 1.1], [2.0, -1.0, 0.5])
    est = Trajectory(gt.timestamps, motion @ gt.poses)
    result = ate(est, gt)
    assert result.rmse < 1e-9 and result.max < 1e-9 and result.n == len(gt)
    np.testing.assert_allclose(result.transform, np.linalg.inv(motion), atol=1e-9)
    # Without alignment the same copy is far off: the shift is 2.3 m.
    assert ate(est, gt, align=False).rmse > 1.0


def test_still_camera_ate_is_the_ate_of_a_constant_pose():
    gt = smooth_trajectory()
    still = Trajectory(gt.timestamps, np.repeat(gt.poses[:1], len(gt), axis=0))
    assert still_camera_ate(gt.positions) == pytest.approx(ate(still, gt).rmse, rel=1e-9)
    assert still_camera_ate(gt.positions) > 0.1


def test_ate_of_gaussian_noise_matches_the_noise():
    gt = smooth_trajectory(3000)
    sigma = 0.01
    noisy = gt.poses.copy()
    noisy[:, :3, 3] += np.random.default_rng(7).normal(0, sigma, (len(gt), 3))
    result = ate(Trajectory(gt.timestamps, noisy), gt)
    assert result.rmse == pytest.approx(sigma * np.sqrt(3), rel=0.03)
    assert result.mean == pytest.approx(sigma * 2 * np.sqrt(2 / np.pi), rel=0.03)  # Maxwell distribution mean
    assert result.median <= result.rmse <= result.max


def test_rpe_of_constant_drift_per_frame_and_per_metre():
    n, step, drift, spin = 200, 0.1, 0.002, np.radians(0.5)  # per frame: 10 cm forward, 2 mm and 0.5 deg drift
    k = np.arange(n)
    gt_poses = np.tile(np.eye(4), (n, 1, 1))
    gt_poses[:, 2, 3] = step * k
    est_poses = gt_poses.copy()
    est_poses[:, 2, 3] = (step + drift) * k
    est_poses[:, :3, :3] = Rotation.from_rotvec(np.outer(spin * k, [0, 0, 1])).as_matrix()
    gt, est = Trajectory(k / 30.0, gt_poses), Trajectory(k / 30.0, est_poses)

    per_frame = rpe(est, gt, delta=1, unit="frames")
    assert per_frame.n == n - 1
    assert per_frame.trans_rmse == pytest.approx(drift, abs=1e-12)
    assert per_frame.rot_rmse == pytest.approx(0.5, abs=1e-9)
    per_metre = rpe(est, gt, delta=1.0, unit="metres")  # 1 m = 10 frames of ground truth
    assert per_metre.n == n - 10
    assert per_metre.trans_mean == pytest.approx(10 * drift, abs=1e-12)
    assert per_metre.rot_mean == pytest.approx(5.0, abs=1e-9)
    with pytest.raises(TrajectoryError, match="no pose pairs 100.0 metres apart"):
        rpe(est, gt, delta=100.0, unit="metres")


# ---------------------------------------------------------------------------------------------------------------
# Reconstruction metrics


def test_sample_surface_is_area_weighted_and_seeded():
    small, large = square_plane(1.0, z=0.0, divisions=1), square_plane(np.sqrt(3.0), z=5.0, divisions=1)
    both = trimesh.util.concatenate([small, large])
    points = sample_surface(both, 40_000, seed=3)
    assert np.mean(points[:, 2] > 1) == pytest.approx(0.75, abs=0.01)
    assert np.abs(points[:, :2]).max() <= np.sqrt(3.0) / 2 + 1e-12
    np.testing.assert_array_equal(points, sample_surface(both, 40_000, seed=3))
    assert not np.array_equal(points, sample_surface(both, 40_000, seed=4))


def test_mesh_against_itself_scores_zero_and_full_completion():
    mesh = room(subdivisions=1)
    result = reconstruction_metrics(mesh, mesh, n_points=20_000)
    assert result.accuracy == 0.0 and result.completion == 0.0
    assert result.completion_ratio == 1.0
    assert all(s.precision == s.recall == s.fscore == 1.0 for s in result.scores)


def test_plane_shifted_by_one_centimetre_scores_one_centimetre():
    gt = square_plane(1.0, z=0.0)
    rec = square_plane(1.0, z=0.01)
    result = reconstruction_metrics(rec, gt, n_points=100_000, thresholds=(0.005, 0.05))
    # Every sample is 1 cm off the other plane (plus at most the in-plane gap between samples).
    assert result.accuracy == pytest.approx(0.01, abs=3e-4)
    assert result.completion == pytest.approx(0.01, abs=3e-4)
    assert result.completion_ratio == 1.0
    five_mm, five_cm = result.scores
    assert five_mm.precision == five_mm.recall == five_mm.fscore == 0.0  # nothing is closer than 5 mm
    assert five_cm.precision == five_cm.recall == five_cm.fscore == 1.0
    # A differently triangulated copy samples independent points: the in-plane gap (~1 mm at 100k per m^2) shows.
    independent = reconstruction_metrics(square_plane(1.0, z=0.01, divisions=5), gt, n_points=100_000)
    assert 0.0100 <= independent.accuracy < 0.0105


def test_completion_sees_missing_surface_and_accuracy_does_not():
    gt = square_plane(2.0, divisions=8)
    # The reconstruction covers only the x < 0 half of the ground truth.
    half = gt.copy()
    half.update_faces(half.triangles_center[:, 0] < 0)
    half.remove_unreferenced_vertices()
    result = reconstruction_metrics(half, gt, n_points=50_000)
    assert result.accuracy < 0.005
    assert result.completion_ratio == pytest.approx(0.5 + 0.05 / 2.0, abs=0.01)  # the half plus a 5 cm band
    assert result.completion == pytest.approx(0.25, abs=0.01)  # half the samples at 0, half at 0.5 m on average


def test_icp_recovers_a_small_known_transform():
    gt = asymmetric_scene()
    offset = rigid(np.radians([1.5, -1.0, 2.0]), [0.03, -0.02, 0.015])
    rec = gt.copy()
    rec.apply_transform(offset)
    transform = icp_align(rec, gt, n_points=20_000)
    aligned = rec.vertices @ transform[:3, :3].T + transform[:3, 3]
    assert np.abs(aligned - gt.vertices).max() < 0.003
    np.testing.assert_allclose(transform, np.linalg.inv(offset), atol=3e-3)


def test_bad_meshes_are_rejected_with_the_reason(tmp_path):
    with pytest.raises(MeshError, match="empty"):
        check_mesh(trimesh.Trimesh(), "reconstructed mesh")
    nan_mesh = square_plane()
    nan_mesh.vertices[3] = [np.nan, 0, 0]
    with pytest.raises(MeshError, match="nan"):
        check_mesh(nan_mesh, "reconstructed mesh")
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], process=False)
    with pytest.raises(MeshError, match="zero total area"):
        check_mesh(flat, "ground-truth mesh")
    with pytest.raises(MeshError, match="missing.ply"):
        load_mesh(tmp_path / "missing.ply", "ground-truth mesh")
    with pytest.raises(MeshError, match="empty"):
        reconstruction_metrics(trimesh.Trimesh(), room(), n_points=100)


def test_open_meshes_only_warn(caplog):
    check_mesh(square_plane(), "partial reconstruction")
    assert "not watertight" in caplog.text


# ---------------------------------------------------------------------------------------------------------------
# Depth L1


def test_depth_l1_of_a_mesh_against_itself_is_zero_and_seeded():
    scene = room()
    first = depth_l1(scene, scene, n_views=15, seed=5, width=40, height=30)
    assert first.mean == 0.0 and first.n_views == 15 and first.missing_fraction == 0.0
    again = depth_l1(scene, scene, n_views=15, seed=5, width=40, height=30)
    np.testing.assert_array_equal(first.poses, again.poses)
    # Cameras are inside the room (bounding box shrunk by 10 % per side).
    assert np.all(np.abs(first.poses[:, :3, 3]) <= np.array([4.0, 3.0, 2.5]) * 0.4 + 1e-12)


def test_depth_l1_of_a_plane_shifted_by_one_centimetre_is_one_centimetre():
    gt, rec = square_plane(6.0, z=0.0), square_plane(6.0, z=0.01)
    # Cameras 1 m above the plane looking straight down: every pixel sees both planes 1 cm apart.
    poses = [look_at(np.array([x, y, 1.0]), np.array([x, y, 0.0])) for x, y in [(0, 0), (0.5, -0.3), (-1, 1)]]
    result = depth_l1(rec, gt, poses=np.stack(poses), width=40, height=30)
    assert result.mean == pytest.approx(0.01, abs=2e-6)
    assert result.n_views == 3 and result.missing_fraction == 0.0
    # Random views see the planes obliquely, but always at least 1 cm apart along z; the room rejects none.
    scene = room(subdivisions=1)
    shifted = scene.copy()
    shifted.apply_translation([0, 0, 0.01])
    random_views = depth_l1(shifted, scene, n_views=10, width=40, height=30)
    assert 0.0 < random_views.mean < 0.02


def test_depth_l1_rejects_views_without_ground_truth_surface():
    plane = square_plane(1.0)
    with pytest.raises(MeshError, match="none of 20 random views"):
        depth_l1(plane, plane, n_views=1, width=20, height=15, max_attempts_factor=20, min_valid_fraction=0.99)


# ---------------------------------------------------------------------------------------------------------------
# Plots


def _is_png(path: Path) -> bool:
    return path.is_file() and path.stat().st_size > 1000 and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_plots_are_written(tmp_path):
    traj = smooth_trajectory(100)
    result = ate(traj, traj)
    assert _is_png(plots.plot_trajectory(result.gt_positions, result.aligned_positions, tmp_path / "a" / "traj.png"))
    assert _is_png(plots.plot_position_error(result.timestamps, result.errors + 0.01, tmp_path / "err.png"))
    depth = np.linspace(1, 3, 12 * 16, dtype=np.float32).reshape(12, 16)
    holes = depth.copy()
    holes[:4] = 0
    assert _is_png(plots.plot_depth_errors([(depth, holes), (depth, depth + 0.01)], tmp_path / "depth.png"))


# ---------------------------------------------------------------------------------------------------------------
# Run directory report and command line

INTR = Intrinsics(width=48, height=36, fx=24.0, fy=24.0, cx=23.5, cy=17.5)


class FakeDataset:
    """Stands in for eslam_core.datasets: frames rendered from the ground-truth room at the given poses."""

    def __init__(self, scene: trimesh.Trimesh, poses: np.ndarray, ground_truth: bool = True):
        self.intrinsics = INTR
        self.frames = []
        for i, pose in enumerate(poses):
            depth, _ = render_depth(scene, INTR, pose)
            self.frames.append(Frame(i, i / 30.0, np.zeros((36, 48, 3), np.uint8), depth,
                                     pose if ground_truth else None))

    def timestamps(self):
        return np.array([frame.timestamp for frame in self.frames])

    def subset(self, start=0, stop=None, stride=1):
        view = FakeDataset.__new__(FakeDataset)
        view.intrinsics, view.frames = self.intrinsics, self.frames[start:stop:stride]
        return view

    def __len__(self):
        return len(self.frames)

    def __getitem__(self, i):
        return self.frames[i]


def make_run(folder: Path, gt: Trajectory, est: Trajectory, mesh=None, data=None, seconds_per_frame=0.5) -> Path:
    folder.mkdir(parents=True)
    write_tum(folder / "trajectory.txt", est)
    write_tum(folder / "groundtruth.txt", gt)
    if mesh is not None:
        mesh.export(folder / "mesh.ply")
    summary = {
        "data": str(data) if data else None, "dataset_kind": "replica", "frames": [0, None, 1],
        "n_frames": len(gt), "seconds_per_frame": seconds_per_frame, "frames_per_second": 1 / seconds_per_frame,
        "peak_memory_mb": 812.0, "parameter_count": 123456, "truncation": 0.06, "ate_rmse_cm": None,
        "config_file": "config/replica.yaml",
    }
    (folder / "summary.json").write_text(json.dumps(summary))
    (folder / "config.yaml").write_text(yaml.safe_dump({"name": "replica", "tracking": {"iterations": 8}}))
    return folder


def room_trajectory(n: int = 12) -> Trajectory:
    """Cameras inside the 4 x 3 x 2.5 m room, turning on the spot while sliding 0.6 m along x."""
    poses = []
    for k in range(n):
        yaw = np.radians(-40 + 80 * k / (n - 1))
        position = np.array([-0.3 + 0.6 * k / (n - 1), 0.0, 0.0])
        poses.append(look_at(position, position + [np.cos(yaw), np.sin(yaw), -0.2]))
    return Trajectory(np.arange(n) / 30.0, np.stack(poses))


def test_evaluate_run_trajectory_only_and_markdown(tmp_path):
    gt = smooth_trajectory(120)
    noisy = gt.poses.copy()
    noisy[:, :3, 3] += np.random.default_rng(0).normal(0, 0.02, (len(gt), 3))
    run = make_run(tmp_path / "run", gt, Trajectory(gt.timestamps, rigid([0, 0, 0.5], [1, 2, 3]) @ noisy))
    report = evaluate_run(run, depth_views=0)
    expected = ate(read_tum(run / "trajectory.txt"), read_tum(run / "groundtruth.txt"))
    assert report["trajectory"]["ate_rmse_cm"] == pytest.approx(100 * expected.rmse, rel=1e-9)
    assert 2.5 < report["trajectory"]["ate_rmse_cm"] < 4.5  # ~ 2 cm x sqrt(3)
    assert report["trajectory"]["rpe_per_metre"]["pairs"] > 0
    assert report["reconstruction"] is None
    assert any("no mesh.ply" in reason for reason in report["skipped"])
    assert report["performance"]["peak_memory_mb"] == 812.0
    for name in ("trajectory", "position_error"):
        assert _is_png(run / report["plots"][name])
    markdown = render_markdown(report)
    assert "| ATE RMSE |" in markdown and "plots/trajectory.png" in markdown and "iterations: 8" in markdown
    json.loads(write_report_json(report, run / "report.json").read_text())


def test_evaluate_run_compares_the_errors_with_the_predicted_sigma(tmp_path):
    """pose_quality.csv's covariance against the errors: 2 cm noise per axis (3.5 cm per position) predicted by a
    sigma of 3.5 cm gives a median ratio near 1 (0.9: the median of a chi distribution with 3 degrees of freedom
    over its RMS); a tenfold overconfident covariance gives ten times that."""
    from eslam_core.outputs.export import tracking_table
    from eslam_core.trajectory import TrackedTrajectory

    gt = smooth_trajectory(120)
    noisy = gt.poses.copy()
    noisy[:, :3, 3] += np.random.default_rng(0).normal(0, 0.02, (len(gt), 3))
    for scale, expected in ((1.0, 0.9), (0.1, 9.0)):
        run = make_run(tmp_path / f"run{scale}", gt, Trajectory(gt.timestamps, noisy))
        records = TrackedTrajectory()
        for k, t in enumerate(gt.timestamps):
            records.record(k, t, noisy[k], 0.1, None, k == 0, 1.0, False, k == 5,
                           np.diag([(0.02 * scale) ** 2] * 3 + [1e-6] * 3))
        (run / "pose_quality.csv").write_text(tracking_table(records))
        report = evaluate_run(run, depth_views=0, consistency_frames=0)
        covariance = report["trajectory"]["covariance"]
        assert covariance["frames_degraded"] == 1 and covariance["frames_lost"] == 0
        assert covariance["error_over_sigma_median"] == pytest.approx(expected, rel=0.15)
        assert "| error / predicted sigma, median |" in render_markdown(report)
        assert _is_png(run / report["plots"]["position_error"])


def test_evaluate_run_culls_both_meshes_and_scores_reconstruction(tmp_path, monkeypatch):
    scene = room()
    traj = room_trajectory()
    fake = types.ModuleType("eslam_core.datasets")
    fake.open_dataset = lambda path, kind="auto", **overrides: FakeDataset(scene, traj.poses)
    monkeypatch.setitem(sys.modules, "eslam_core.datasets", fake)
    data = tmp_path / "data"
    data.mkdir()
    scene.export(tmp_path / "gt.ply")
    shifted = scene.copy()
    shifted.apply_translation([0.01, 0, 0])
    run = make_run(tmp_path / "run", traj, traj, mesh=shifted, data=data)

    # 200k samples on the ~17 m^2 of observed walls: sample gaps (~5 mm) stay below the 1 cm shift.
    report = evaluate_run(run, gt_mesh=tmp_path / "gt.ply", n_points=200_000, depth_views=10)
    culling = report["reconstruction"]["culling"]
    assert culling["cameras"] == len(traj)
    # The cameras look at part of the room only: both meshes lose faces, and by similar amounts.
    assert 0 < culling["gt_faces"][1] < culling["gt_faces"][0]
    assert abs(culling["rec_faces"][1] - culling["gt_faces"][1]) < 0.1 * culling["gt_faces"][1]
    # A 1 cm shift along x: walls facing x are 1 cm off, the others slide along themselves.
    assert 0.3 < report["reconstruction"]["accuracy_cm"] < 1.2
    assert report["reconstruction"]["completion_ratio_percent"] > 99.0
    assert report["depth_l1"]["views"] == 10 and 0.0 < report["depth_l1"]["depth_l1_cm"] < 2.0
    assert report["consistency"] is None and any("depth consistency: no two frames" in r for r in report["skipped"])
    assert _is_png(run / report["plots"]["depth_errors"])
    assert report["trajectory"]["ate_rmse_cm"] < 1e-6


def test_evaluate_run_scores_depth_consistency_with_and_without_ground_truth(tmp_path, monkeypatch):
    scene = room()
    traj = room_trajectory(30)
    shaken = traj.poses.copy()
    shaken[:, :3, 3] += np.random.default_rng(1).normal(0.0, 0.02, (len(shaken), 3))  # positions ~3.5 cm off
    estimate = Trajectory(traj.timestamps, shaken)
    data = tmp_path / "data"
    data.mkdir()
    fake = types.ModuleType("eslam_core.datasets")
    fake.open_dataset = lambda path, kind="auto", **overrides: FakeDataset(scene, traj.poses)
    monkeypatch.setitem(sys.modules, "eslam_core.datasets", fake)

    run = make_run(tmp_path / "run", traj, estimate, data=data)
    report = evaluate_run(run, depth_views=0)
    consistency = report["consistency"]
    assert consistency["frames"] == 30 and consistency["estimate"]["pairs"] >= 15
    assert consistency["reference"]["median_mm"] < 0.01  # exact poses, exact depth
    assert consistency["reference"]["agree_percent"] == 100.0
    assert consistency["estimate"]["median_mm"] > 5.0
    assert consistency["estimate"]["pairs"] == consistency["reference"]["pairs"]  # scored on the same pairs
    assert _is_png(run / report["plots"]["depth_consistency"])
    markdown = render_markdown(report)
    assert "## Depth consistency" in markdown and "reference poses" in markdown

    # without ground truth (no groundtruth.txt, frames without poses) the estimate is still scored
    fake.open_dataset = lambda path, kind="auto", **overrides: FakeDataset(scene, traj.poses, ground_truth=False)
    (run / "groundtruth.txt").unlink()
    report = evaluate_run(run, depth_views=0, plots=False)
    assert report["trajectory"] is None and report["consistency"]["reference"] is None
    assert report["consistency"]["estimate"]["median_mm"] > 5.0
    assert "reference poses" not in render_markdown(report)

    # no data set: skipped, with the reason
    report = evaluate_run(run, data=tmp_path / "moved", depth_views=0, plots=False)
    assert report["consistency"] is None and any("depth consistency: data set not found" in r
                                                 for r in report["skipped"])


def test_cli_evaluates_compares_and_reports_errors(tmp_path, capsys):
    gt = smooth_trajectory(60)
    slow = make_run(tmp_path / "a" / "out", gt, gt, seconds_per_frame=2.0)
    shifted = gt.poses.copy()
    shifted[1::2, 0, 3] += 0.01
    fast = make_run(tmp_path / "b" / "out", gt, Trajectory(gt.timestamps, shifted), seconds_per_frame=0.5)
    for run in (slow, fast):
        assert cli.main([str(run), "--no-plots", "--depth-views", "0"]) == 0
        assert (run / "report.json").is_file() and (run / "report.md").is_file()
        assert not (run / "plots").exists()
    out = tmp_path / "compare.md"
    assert cli.main(["--compare", str(slow), str(fast), "--out", str(out)]) == 0
    text = out.read_text()
    assert "a/out" in text and "b/out" in text and "| Seconds per frame | 2.000 | 0.500 | -1.500 |" in text
    assert compare_runs(slow, fast) == text

    capsys.readouterr()
    assert cli.main([str(tmp_path / "missing")]) == 2
    assert "run directory not found" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert cli.main(["--compare", str(slow), str(tmp_path / "empty")]) == 2
    assert "no report.json" in capsys.readouterr().err
    with pytest.raises(RunDirectoryError, match="summary.json"):
        evaluate_run(tmp_path / "empty")


def test_module_entry_point_runs(tmp_path):
    completed = subprocess.run(
        [sys.executable, "-m", "eslam_core.evaluation.cli", str(tmp_path / "nowhere")],
        capture_output=True, text=True, timeout=60, cwd=Path(__file__).resolve().parents[1],
    )
    assert completed.returncode == 2 and "run directory not found" in completed.stderr
