"""A short run on the synthetic room: trajectory and mesh against ground truth, checkpoint, re-mesh and resume."""
import json

import numpy as np
import pytest
import torch
import trimesh
from torch.optim.optimizer import register_optimizer_step_post_hook

from eslam_core.cli import main
from eslam_core.config import load_config
from eslam_core.demo import mesh_scores
from eslam_core.evaluation.trajectory_error import still_camera_ate
from eslam_core.outputs.export import load_checkpoint, map_mesh
from eslam_core.mapping.keyframes import Keyframe
from eslam_core.runner import run_sequence

FAST = {"mapping": {"first_iterations": 200}, "mesh": {"resolution": 0.03}}


@pytest.fixture(scope="module")
def run(room_sequence, tmp_path_factory):
    torch.manual_seed(0)
    out = tmp_path_factory.mktemp("run")
    summary = run_sequence(load_config("demo", FAST), room_sequence, out, progress=False)
    return summary, out


def test_trajectory_accuracy(run):
    summary, out = run
    assert summary.n_frames == 30
    est = np.loadtxt(out / "trajectory.txt")
    gt = np.loadtxt(out / "groundtruth.txt")
    assert 2.0 < 0.5 * 100 * still_camera_ate(gt[:, 1:4])  # a camera that never moves is 8 cm off
    assert summary.ate_rmse_cm is not None and summary.ate_rmse_cm < 2.0
    assert est.shape == gt.shape == (30, 8)
    assert np.allclose(est[:, 0], gt[:, 0])


def test_mesh_accuracy(run, room_sequence):
    summary, out = run
    scores = mesh_scores(out / "mesh.ply", room_sequence.root / "mesh.ply", room_sequence, 0.06, n_points=100_000)
    assert scores.accuracy < 0.02
    assert scores.completion < 0.03 and scores.completion_ratio > 0.9


def test_summary_and_config_recorded(run):
    summary, out = run
    s = json.loads((out / "summary.json").read_text())
    assert s["n_frames"] == 30 and s["ate_rmse_cm"] == pytest.approx(summary.ate_rmse_cm)
    assert s["parameter_count"] > 1e5 and s["peak_memory_mb"] > 0 and s["seconds_per_frame"] > 0
    assert s["keyframes"] == 8  # frames 0, 4, ..., 28
    assert load_config(out / "config.yaml").mapping.first_iterations == 200


def test_keyframes_are_compact(run):
    slam = load_checkpoint(run[1] / "checkpoint.pt")
    kf = slam.map.keyframes[-1]
    h, w = kf.rgb.shape[:2]
    assert kf.rgb.dtype == torch.uint8 and kf.depth.element_size() == 2
    assert kf.nbytes() / (h * w) * 640 * 480 < 2 * 2**20  # under 2 MB at 640x480


def test_keyframe_depth_roundtrip():
    depth = torch.tensor([[0.0, 0.5, 4.2], [9.9, 13.0, 20.0]])
    kf = Keyframe.from_tensors(0, 0.0, torch.zeros(2, 3, 3), depth, torch.ones(2, 3, dtype=torch.bool), torch.eye(4))
    back = kf.depth_image()
    assert torch.allclose(back[depth < 13.1], depth[depth < 13.1], atol=1e-4)
    assert back[1, 2] == 0  # beyond the 16-bit range: stored as missing rather than wrapped


def test_checkpoint_remesh_at_other_resolution(run, tmp_path):
    slam = load_checkpoint(run[1] / "checkpoint.pt")
    coarse = map_mesh(slam, 0.06)
    fine = trimesh.load(run[1] / "mesh.ply", process=False)
    assert 0 < len(coarse.faces) < len(fine.faces)
    assert main(["mesh", str(run[1] / "checkpoint.pt"), "--resolution", "0.05", "--out", str(tmp_path / "m.ply")]) == 0
    assert len(trimesh.load(tmp_path / "m.ply").faces) > 100


def test_resume_continues_where_the_checkpoint_stopped(room_sequence, run, tmp_path):
    """Resume the 30-frame run on 4 more... frames of the same data: only frames not yet processed are run."""
    summary, out = run
    first = room_sequence.subset(0, 30)
    resumed = run_sequence(load_config("demo", FAST), first, tmp_path, resume=out / "checkpoint.pt",
                           progress=False, write_mesh=False)
    assert resumed.n_frames == 0  # nothing left to do
    slam = load_checkpoint(tmp_path / "checkpoint.pt")
    assert len(slam.trajectory) == 30
    assert np.allclose(slam.trajectory.poses(), load_checkpoint(out / "checkpoint.pt").trajectory.poses())


def test_resume_through_the_pipelined_runtime_runs_only_the_frames_not_done(room_sequence, tmp_path):
    """--resume with --workers 2: the runtime starts in the checkpoint's map and trajectory and gets only the frames
    the checkpoint has not seen; the poses it had stay as they were (the demo maps without joint pose refinement
    here, so nothing moves them)."""
    cfg = load_config("demo", {**FAST, "mapping": {"first_iterations": 60, "joint_poses": False}})
    first = run_sequence(cfg, room_sequence.subset(0, 12), tmp_path / "a", progress=False, write_mesh=False)
    resumed = run_sequence(cfg, room_sequence.subset(0, 16), tmp_path / "b", resume=tmp_path / "a" / "checkpoint.pt",
                           progress=False, write_mesh=False, workers=2)
    assert first.n_frames == 12 and resumed.n_frames == 4
    before, after = (load_checkpoint(tmp_path / d / "checkpoint.pt").trajectory for d in ("a", "b"))
    assert len(after) == 16 and np.allclose(after.timestamps(), room_sequence.subset(0, 16).timestamps())
    assert np.allclose(after.poses()[:12], before.poses(), atol=1e-6)


def test_checkpoint_restores_observed_space(run):
    """The fast tracker's observed space is rebuilt from the keyframes when a checkpoint is loaded."""
    summary, out = run
    slam = load_checkpoint(out / "checkpoint.pt")
    observed = slam.map.observed.space
    assert observed.seen.any()
    kf = slam.map.keyframes[-1]
    d = kf.depth_image()
    v, u = (int(x) for x in torch.nonzero(d > 0)[len(torch.nonzero(d > 0)) // 2])
    seen_point = slam.dirs_cam[v * d.shape[1] + u] * d[v, u] @ kf.pose[:3, :3].T + kf.pose[:3, 3]
    camera_centre = kf.pose[:3, 3]  # the camera sits in free space, away from every surface
    assert observed.contains(torch.stack([seen_point, camera_centre])).tolist() == [True, False]


@pytest.mark.parametrize("joint_poses", [True, False])
def test_joint_pose_switch(room_sequence, joint_poses):
    """mapping.joint_poses: False keeps the tracked keyframe poses as they are; True lets mapping refine them."""
    from eslam_core.slam import SLAM

    cfg = load_config("demo", {"mapping": {"first_iterations": 20, "iterations": 5, "joint_poses_after": 0,
                                           "joint_poses": joint_poses},
                               "tracking": {"iterations": 3}})
    slam = SLAM(cfg, room_sequence.intrinsics)
    tracked = {}  # frame -> the pose tracking gave it, before mapping
    track = slam.tracking.frontend.tracker.track
    slam.tracking.frontend.tracker.track = lambda field, frame, *args, **kw: tracked.setdefault(frame.index, track(field, frame, *args,
                                                                                                   **kw))
    for i in range(9):
        slam.step(room_sequence[i])
    # (beyond the re-orthonormalisation of a tracked pose, ~1e-7)
    moved = [float((kf.pose - tracked[kf.frame_index].pose).abs().max()) > 1e-5 for kf in slam.map.keyframes[1:]]
    assert [kf.frame_index for kf in slam.map.keyframes] == [0, 4, 8]
    assert any(moved) == joint_poses


def test_diverged_tracking_keeps_the_prediction(room_sequence, caplog):
    """A tracker that returns a non-finite pose must not end the run with an unwritable trajectory: the frame keeps
    the pose it was predicted at (and counts as lost)."""
    from eslam_core.slam import SLAM
    from eslam_core.tracking.result import TrackingResult

    cfg = load_config("demo", {"mapping": {"first_iterations": 10, "iterations": 2}, "tracking": {"iterations": 2}})
    slam = SLAM(cfg, room_sequence.intrinsics)
    track = slam.tracking.frontend.tracker.track
    predicted = {}

    def diverging(field, frame, init, *args, **kw):
        if frame.index == 2:
            predicted[2] = init.double().numpy()
            return TrackingResult(torch.full((4, 4), float("nan")), float("nan"), 0)
        return track(field, frame, init, *args, **kw)

    slam.tracking.frontend.tracker.track = diverging
    results = [slam.step(room_sequence[i]) for i in range(4)]
    poses = slam.trajectory.poses()
    assert np.isfinite(poses).all()
    assert np.allclose(poses[2], predicted[2], atol=1e-5) and results[2].lost
    assert "tracking diverged" in caplog.text


def test_depth_outside_the_bound_is_counted_and_not_used(room_sequence):
    from eslam_core.slam import SLAM

    bound = [[-2.1, -1.6, -0.1], [0.3, 1.6, 2.7]]  # cuts the room at x = 0.3 m (before growing to the grid)
    cfg = load_config("demo", {"scene": {"bound": bound}, "mapping": {"first_iterations": 1}})
    slam = SLAM(cfg, room_sequence.intrinsics)
    slam.step(room_sequence[0])
    kf = slam.map.keyframes[0]
    d = kf.depth_image()
    points = (slam.dirs_cam * d.reshape(-1, 1)) @ kf.pose[:3, :3].T + kf.pose[:3, 3]
    x_max = slam.map.extent[1][0]
    beyond = (points[:, 0] > x_max + 0.01) & (d.reshape(-1) > 0)
    inside = (points[:, 0] < x_max - 0.01) & (d.reshape(-1) > 0)
    assert beyond.sum() > 100 and inside.sum() > 100
    usable = kf.usable.reshape(-1)
    assert not usable[beyond].any() and usable[inside].all()
    assert slam.map.points_outside >= int(beyond.sum())


@pytest.mark.parametrize("usable_fraction", [0.9, 0.001])
def test_mapping_draws_only_usable_pixels(usable_fraction):
    """Rejection sampling for the usual mostly-usable keyframe, a full pass for a sparse one: same answer."""
    from eslam_core.frames import pixel_directions_table
    from eslam_core.camera import Intrinsics
    from eslam_core.mapping.mapper import Mapper

    cfg = load_config("demo", {"mapping": {"border": 5}})
    intr = Intrinsics(width=80, height=60, fx=70.0, fy=70.0, cx=39.5, cy=29.5)
    g = torch.Generator().manual_seed(1)
    usable = torch.rand(60, 80, generator=g) < usable_fraction
    kf = Keyframe.from_tensors(0, 0.0, torch.rand(60, 80, 3), torch.full((60, 80), 2.0), usable, torch.eye(4))
    mapper = Mapper.of(cfg, pixel_directions_table(intr), 60, 80)
    pix = mapper._pixels(kf, 500)
    v, u = pix // 80, pix % 80
    assert len(pix) == 500
    assert usable.reshape(-1)[pix].all()
    assert ((u >= 5) & (u < 75) & (v >= 5) & (v < 55)).all()
    assert len(torch.unique(pix)) > min(200, int(usable[5:55, 5:75].sum()) - 1)


def test_mapping_step_can_end_early(room_sequence):
    """SLAM.after_mapping_iteration (the runtimes' per-iteration callback) ends a regular mapping step once it says
    so; the warm-up runs all its iterations whatever it says."""
    from eslam_core.slam import SLAM

    cfg = load_config("demo", {"mapping": {"first_iterations": 20, "iterations": 10}, "tracking": {"iterations": 2}})
    slam = SLAM(cfg, room_sequence.intrinsics)
    asked = []
    slam.after_mapping_iteration = lambda done: asked.append(done) or done >= 3
    steps = []
    hook = register_optimizer_step_post_hook(lambda opt, args, kw: steps.append(1) if opt.defaults["fused"] else None)
    try:
        for i in range(5):  # frame 0: the warm-up (never cut short); frame 4: a keyframe, cut after 3 iterations
            slam.step(room_sequence[i])
    finally:
        hook.remove()
    assert len(steps) == 20 + 3  # mapping's optimiser is the fused Adam (the rendering tracker's is not)
    assert asked == list(range(1, 21)) + [1, 2, 3]
