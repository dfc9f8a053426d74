"""Tracking converges to the true pose against a map fitted to the synthetic room."""
import numpy as np
import pytest
import torch

from eslam_core.mapping.extent import grow_to_multiple
from eslam_core.config import load_config
from eslam_core.representation.field import SceneField
from eslam_core.frames import pixel_directions_table, prepare_frame
from eslam_core.geometry import depth_points_world, rotation_angle_deg, so3_exp
from eslam_core.mapping.keyframes import Keyframe
from eslam_core.mapping.mapper import Mapper
from eslam_core.mapping.extent import draw_in_extent
from eslam_core.tracking.render_tracker import Tracker, constant_velocity, outlier_mask


def axis_angle(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.radians(deg)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


@pytest.fixture(scope="module")
def fitted_map(room_sequence):
    """Map fitted with ground-truth poses to frames 0, 6, 12 (no tracking involved)."""
    torch.manual_seed(0)
    cfg = load_config("demo", {"mapping": {"rays": 3000}})
    ds = room_sequence
    bound = grow_to_multiple(np.array([[-2.1, -1.6, -0.1], [2.1, 1.6, 2.7]]), cfg.model.coarse_resolution)
    field = SceneField(bound, cfg.model)
    dirs = pixel_directions_table(ds.intrinsics)
    kfs = []
    for i in (0, 6, 12):
        f = prepare_frame(ds[i], ds.intrinsics, cfg.camera)
        kfs.append(Keyframe.from_tensors(i, f.timestamp, f.rgb, f.depth, f.depth >= 0,
                                         torch.from_numpy(f.gt_pose).float()))
    mapper = Mapper.of(cfg, dirs, ds.intrinsics.height, ds.intrinsics.width)
    cfg.mapping.first_iterations = 250
    mapper.map(field, kfs, [0, 1, 2], first=True)
    return cfg, field, dirs


def test_tracking_recovers_perturbed_pose(fitted_map, room_sequence):
    cfg, field, dirs = fitted_map
    cfg.tracking.iterations = 100
    cfg.render_tracker.lr_translation = 0.003
    cfg.render_tracker.lr_rotation = 0.002
    ds = room_sequence
    frame = prepare_frame(ds[9], ds.intrinsics, cfg.camera)
    gt = frame.gt_pose
    start = gt.copy()
    start[:3, :3] = axis_angle([0.3, 1.0, -0.2], 3.0) @ gt[:3, :3]
    start[:3, 3] += np.array([0.02, -0.015, 0.015])  # 3 cm
    assert np.linalg.norm(start[:3, 3] - gt[:3, 3]) == pytest.approx(0.029, abs=0.002)
    tracker = Tracker.of(cfg, dirs, ds.intrinsics.height, ds.intrinsics.width)
    result = tracker.track(field, frame, torch.from_numpy(start).float())
    est = result.pose.double().numpy()
    t_err = np.linalg.norm(est[:3, 3] - gt[:3, 3])
    r_err = rotation_angle_deg(est[:3, :3].T @ gt[:3, :3])
    assert t_err < 0.01, f"translation error {t_err * 100:.2f} cm"
    assert r_err < 0.5, f"rotation error {r_err:.2f} deg"


def test_constant_velocity_repeats_last_motion():
    a = np.eye(4)
    b = np.eye(4)
    b[:3, :3] = axis_angle([0, 0, 1], 2.0)
    b[:3, 3] = [0.01, 0.0, 0.02]
    c = constant_velocity(a, b)
    assert np.allclose(np.linalg.inv(b) @ c, np.linalg.inv(a) @ b)
    assert np.allclose(constant_velocity(None, b), b)


@pytest.mark.parametrize("angle_deg", [0.0, 1e-4, 0.5, 30.0, 170.0])
def test_so3_exp_is_the_rotation_of_the_rotation_vector(angle_deg):
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    R = so3_exp(torch.from_numpy(axis * np.radians(angle_deg))).numpy()
    np.testing.assert_allclose(R, axis_angle(axis, angle_deg), atol=1e-12)


def test_outlier_mask_drops_large_depth_errors():
    err = torch.tensor([0.01, 0.012, 0.009, 0.011, 0.5])
    assert outlier_mask(err, 10.0).tolist() == [True, True, True, True, False]


def _sdf_track_frame_9(cfg, field, dirs, ds, axis, degrees: float, offset, with_keyframe: bool):
    """The SDF tracker on frame 9 from its true pose turned by `degrees` about `axis` and moved by `offset`
    (metres), with frame 6 as the photometric keyframe if asked: (tracker, result, true pose)."""
    from eslam_core.tracking.sdf_tracker import SDFTracker

    keyframe = None
    if with_keyframe:
        f6 = prepare_frame(ds[6], ds.intrinsics, cfg.camera)
        keyframe = Keyframe.from_tensors(6, f6.timestamp, f6.rgb, f6.depth, f6.depth >= 0,
                                         torch.from_numpy(f6.gt_pose).float())
    frame = prepare_frame(ds[9], ds.intrinsics, cfg.camera)
    gt = frame.gt_pose
    start = gt.copy()
    start[:3, :3] = axis_angle(axis, degrees) @ gt[:3, :3]
    start[:3, 3] += np.asarray(offset)
    tracker = SDFTracker.of(cfg, dirs, ds.intrinsics)
    return tracker, tracker.track(field, frame, torch.from_numpy(start).float(), keyframe=keyframe), gt


@pytest.mark.parametrize("color_weight,with_keyframe", [(0.0, False), (1.0, False), (0.0, True), (1.0, True)])
def test_sdf_tracker_recovers_perturbed_pose(fitted_map, room_sequence, color_weight, with_keyframe):
    """The fast Gauss-Newton alignment (depth only, with the map's colour, with the keyframe's images) converges
    from 3 cm / 3 degrees too."""
    cfg, field, dirs = fitted_map
    cfg.tracking.iterations = 15
    cfg.tracking.rays = 3000
    cfg.sdf_tracker.color_weight = color_weight
    tracker, result, gt = _sdf_track_frame_9(cfg, field, dirs, room_sequence, [-0.5, 1.0, 0.4], 3.0,
                                             [-0.015, 0.02, 0.015], with_keyframe)
    assert (tracker._reference is not None) == with_keyframe
    est = result.pose.double().numpy()
    assert np.linalg.norm(est[:3, 3] - gt[:3, 3]) < 0.01
    assert rotation_angle_deg(est[:3, :3].T @ gt[:3, :3]) < 0.5


@pytest.mark.xfail(strict=True, raises=AssertionError, reason="the SDF alignment alone, at the `live` and `fast` settings, does not converge "
                   "from this start: its basin is narrower than 5 cm / 5 degrees. The front end starts it from the "
                   "frame-to-frame odometry instead (test_the_front_end_holds_a_jerk_...)")
@pytest.mark.parametrize("preset", ["live", "fast"])
def test_sdf_tracker_at_the_presets_settings_converges_from_5_cm_and_5_degrees(fitted_map, room_sequence, preset):
    """The convergence basin of the live trackers (the preset's iterations, points, pyramid and photometric term
    against the newest keyframe, 3 frames back): a prediction 5 cm and 5 degrees off, about what a 36 cm/s
    hand-held camera moves in 4 frames at 30 Hz, is corrected to under 1 cm / 0.5 degrees."""
    from dataclasses import replace

    cfg, field, dirs = fitted_map
    cfg = replace(cfg, tracking=replace(load_config(preset).tracking, border=cfg.tracking.border))
    torch.manual_seed(0)
    _, result, gt = _sdf_track_frame_9(cfg, field, dirs, room_sequence, [0.6, -1.0, 0.3], 5.0,
                                       0.05 * np.array([0.6, -0.48, 0.64]), with_keyframe=True)  # 5 cm
    est = result.pose.double().numpy()
    assert np.linalg.norm(est[:3, 3] - gt[:3, 3]) < 0.01
    assert rotation_angle_deg(est[:3, :3].T @ gt[:3, :3]) < 0.5


def test_the_constrained_step_solves_a_linear_problem_and_the_kernel_matches_torch(monkeypatch):
    """Residuals r_i = g_i . (x_i + w x x_i + v) - c_i of points on planes are linear in the motion (v, w): one
    step recovers it exactly; rows of weight 0 take no part; the C kernel's normal equations equal torch's."""
    from eslam_core.native import load_kernel
    from eslam_core.tracking import sdf_tracker
    from eslam_core.tracking.information import constrained_step
    from eslam_core.tracking.sdf_tracker import normal_equations

    g = torch.Generator().manual_seed(0)
    x = torch.randn(500, 3, generator=g, dtype=torch.float64)
    # (gradients of SDF residuals per 1 cm Huber scale: the information that a view constrains, information.py)
    normals = torch.nn.functional.normalize(torch.randn(500, 3, generator=g, dtype=torch.float64), dim=1) / 0.01
    v, w = torch.tensor([0.01, -0.02, 0.005], dtype=torch.float64), torch.tensor([0.003, 0.01, -0.004],
                                                                                 dtype=torch.float64)
    moved = x + torch.cross(w.expand_as(x), x, dim=-1) + v
    r = -(normals * (moved - x)).sum(1)  # the residual at the current pose that the motion cancels
    weights = torch.rand(500, generator=g, dtype=torch.float64)
    weights[:100] = 0.0
    r[:100] = 1e3  # outliers that must not count
    H, b = normal_equations(x, r, normals, weights)
    delta = constrained_step(H.numpy(), b.numpy(), 400, np.array([0.3, -0.2, 1.0]), 1.5)  # every direction
    np.testing.assert_allclose(delta, torch.cat([v, w]).numpy(), rtol=0, atol=1e-9)
    if load_kernel("gauss_newton") is None:
        pytest.skip("no C compiler: the torch implementation is the only one")
    monkeypatch.setattr(sdf_tracker, "load_kernel", lambda name: None)
    H_torch, b_torch = normal_equations(x, r, normals, weights)
    torch.testing.assert_close(H, H_torch, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(b, b_torch, rtol=1e-12, atol=1e-12)


def test_draw_in_extent_keeps_only_points_inside_and_estimates_their_share():
    candidates = torch.arange(0, 2000, 2)  # even pixels; pixel p's point lies at x = p / 1000 m
    torch.manual_seed(0)
    drawn, inside = draw_in_extent(candidates, 500, lambda pix: torch.stack(
        [pix.float() / 1000, torch.zeros(len(pix)), torch.zeros(len(pix))], 1), np.array([[0.0, -1, -1], [0.5, 1, 1]]))
    assert len(drawn) == 500 and (drawn % 2 == 0).all() and (drawn <= 500).all()  # (a second draw filled it)
    assert abs(inside - 0.25) < 0.05
    everything, share = draw_in_extent(candidates, 300, None, None)
    assert len(everything) == 300 and share == 1.0
    assert draw_in_extent(candidates[:0], 10, None, None)[0].numel() == 0


@pytest.mark.parametrize("method", ["render", "sdf"])
def test_trackers_use_only_depth_inside_the_maps_extent(fitted_map, room_sequence, method):
    """A map covering half the room: the trackers see the share of the frame's depth inside it and still
    converge on that half."""
    from eslam_core.tracking.sdf_tracker import SDFTracker

    cfg, field, dirs = fitted_map
    ds = room_sequence
    frame = prepare_frame(ds[9], ds.intrinsics, cfg.camera)
    gt = torch.from_numpy(frame.gt_pose).float()
    d = frame.depth.reshape(-1)
    x = depth_points_world(dirs[d > 0], d[d > 0], gt)[:, 0]
    cut = float(x.median())
    extent = np.array([[-5.0, -5, -5], [cut, 5, 5]])
    start = frame.gt_pose.copy()
    start[:3, 3] += np.array([0.01, -0.01, 0.01])
    tracker = SDFTracker.of(cfg, dirs, ds.intrinsics) if method == "sdf" else Tracker.of(cfg, dirs, ds.intrinsics.height,
                                                                                    ds.intrinsics.width)
    whole = tracker.track(field, frame, torch.from_numpy(start).float())
    half = tracker.track(field, frame, torch.from_numpy(start).float(), extent)
    assert abs(half.depth_fraction - whole.depth_fraction / 2) < 0.06, (half.depth_fraction, whole.depth_fraction)
    assert np.linalg.norm(half.pose[:3, 3].double().numpy() - frame.gt_pose[:3, 3]) < 0.01


def test_constant_velocity_scales_with_the_time_gap():
    from eslam_core.tracking.render_tracker import time_ratio

    a, b = np.eye(4), np.eye(4)
    b[:3, :3] = axis_angle([0, 1, 0], 1.0)
    b[:3, 3] = [0.01, 0.0, 0.0]
    ratio = time_ratio(0.0, 1 / 30, 4 / 30)  # two frames skipped after the last one
    assert ratio == pytest.approx(3.0)
    c = constant_velocity(a, b, ratio)
    step = np.linalg.inv(b) @ c
    assert np.allclose(step[:3, 3], [0.03, 0, 0], atol=1e-9)
    assert rotation_angle_deg(step[:3, :3]) == pytest.approx(3.0)
    assert time_ratio(0.0, 0.0, 1.0) == 1.0 and time_ratio(0.0, 1.0, 100.0) == 4.0


def test_observed_only_draws_rays_from_observed_space(fitted_map, room_sequence):
    """render_tracker.observed_only: candidate pixels are those whose depth point lies in observed space, all of them
    when that would leave fewer than half."""
    from eslam_core.mapping.observed import ObservedSpace

    cfg, field, dirs = fitted_map
    ds = room_sequence
    frame = prepare_frame(ds[9], ds.intrinsics, cfg.camera)
    pose = torch.from_numpy(frame.gt_pose).float()
    depth = frame.depth.reshape(-1)
    candidates = torch.nonzero(depth > 0).squeeze(1)
    points = depth_points_world(dirs[candidates], depth[candidates], pose)
    column = candidates % ds.intrinsics.width
    left = column < 0.75 * ds.intrinsics.width
    tracker = Tracker.of(cfg, dirs, ds.intrinsics.height, ds.intrinsics.width)

    observed = ObservedSpace(field.bound, cfg.model.truncation)
    assert torch.equal(tracker._in_observed_space(candidates, depth, pose, observed), candidates)  # nothing seen
    observed.add(points[left])  # the left three quarters of the view have been mapped
    kept = tracker._in_observed_space(candidates, depth, pose, observed)
    kept_column = kept % ds.intrinsics.width
    assert len(kept) >= left.sum()  # every observed pixel stays...
    assert (kept_column < 0.9 * ds.intrinsics.width).float().mean() > 0.97  # ...and little of the unobserved edge
    assert len(kept) < 0.95 * len(candidates)


def test_frame_odometry_measures_the_motion_between_two_frames_and_says_when_it_cannot(room_sequence):
    """Frames 0 and 9 of the room are 7.8 cm and 4.5 degrees apart: the odometry gets their relative pose within
    3 mm / 0.3 degrees; against a frame with no depth it reports a failure, not a motion."""
    from eslam_core.tracking.odometry import RGBDOdometry

    ds = room_sequence
    cfg = load_config("live")
    f0, f9 = (prepare_frame(ds[i], ds.intrinsics, cfg.camera) for i in (0, 9))
    truth = np.linalg.inv(f0.gt_pose) @ f9.gt_pose
    assert np.linalg.norm(truth[:3, 3]) > 0.07

    def error_of(odometry: RGBDOdometry) -> tuple[float, float]:
        odometry.set_reference(0, odometry.frame(f0.rgb, f0.depth))
        error = np.linalg.inv(truth) @ odometry.motion(odometry.frame(f9.rgb, f9.depth))
        return float(np.linalg.norm(error[:3, 3])), rotation_angle_deg(error[:3, :3])

    odometry = RGBDOdometry(ds.intrinsics, 160)
    assert odometry.motion(odometry.frame(f9.rgb, f9.depth)) is None  # no reference yet
    for odometry in (odometry, RGBDOdometry(ds.intrinsics, 160, iterations=cfg.odometry.iterations)):
        metres, degrees = error_of(odometry)
        assert metres < 0.003 and degrees < 0.3
    assert odometry.motion(odometry.frame(f9.rgb, torch.zeros_like(f9.depth))) is None
    # The iteration counts reach OpenCV: one iteration per level leaves the motion unfinished.
    assert error_of(RGBDOdometry(ds.intrinsics, 160, iterations=(1, 1, 1, 1)))[0] > 3 * metres


@pytest.mark.parametrize("preset", ["live", "fast"])
@pytest.mark.parametrize("last,jump_to", [(13, 22), (10, 22)])
def test_the_front_end_holds_a_jerk_that_the_constant_velocity_prediction_misses(room_sequence, last, jump_to,
                                                                                  preset):
    """The `live` and `fast` presets in lock-step track frames 0..last of the room, then get frame `jump_to` one
    frame gap later: the constant-velocity prediction is 5-8 cm and 2.5-5 degrees off (a jerk of a hand-held camera,
    or frames a live tracker skipped). The frame-to-frame odometry's start puts the pose within 1 cm / 0.5 degrees;
    from the constant-velocity start alone (odometry.width 0) the SDF tracker lands 1.2-5 cm off or loses
    the camera, with either preset."""
    from eslam_core.camera import Frame
    from eslam_core.slam import SLAM
    from eslam_core.tracking.render_tracker import constant_velocity

    ds = room_sequence
    missed = np.linalg.inv(constant_velocity(ds[last - 1].pose, ds[last].pose)) @ ds[jump_to].pose
    assert np.linalg.norm(missed[:3, 3]) > 0.049 and rotation_angle_deg(missed[:3, :3]) > 2.5
    slam = SLAM(load_config(preset, {"mapping": {"first_iterations": 150}}), ds.intrinsics)
    for i in range(last + 1):
        assert not slam.step(ds[i]).lost
    f = ds[jump_to]
    result = slam.step(Frame(f.index, ds[last + 1].timestamp, f.rgb, f.depth, f.pose))
    assert not result.lost
    assert np.linalg.norm(result.pose[:3, 3] - f.pose[:3, 3]) < 0.01
    assert rotation_angle_deg(result.pose[:3, :3].T @ f.pose[:3, :3]) < 0.5
