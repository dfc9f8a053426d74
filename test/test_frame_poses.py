"""Frame poses from keyframe poses: each frame follows its keyframe's mapping correction, blended into the next
keyframe's correction as it nears that keyframe."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from eslam_core.geometry import interpolate_pose, rotation_angle_deg, rotvec_to_matrix
from eslam_core.trajectory import TrackedTrajectory, thinned


def pose(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    T[0, 3] = x
    return T


def test_interpolate_pose_follows_the_geodesic():
    a, b = pose(0.0, 10.0), pose(2.0, 50.0)
    assert np.allclose(interpolate_pose(a, b, 0.0), a) and np.allclose(interpolate_pose(a, b, 1.0), b)
    mid = interpolate_pose(a, b, 0.25)
    assert mid[0, 3] == pytest.approx(0.5)
    assert rotation_angle_deg(a[:3, :3].T @ mid[:3, :3]) == pytest.approx(10.0)
    assert rotation_angle_deg(mid[:3, :3].T @ b[:3, :3]) == pytest.approx(30.0)
    rng = np.random.default_rng(0)
    for _ in range(20):  # any axis, angles up to a half turn: scipy's slerp agrees
        ra, rb = Rotation.random(2, random_state=rng)
        a, b = np.eye(4), np.eye(4)
        a[:3, :3], b[:3, :3] = ra.as_matrix(), rb.as_matrix()
        t = rng.uniform()
        expected = Slerp([0, 1], Rotation.concatenate([ra, rb]))([t]).as_matrix()[0]
        assert np.allclose(interpolate_pose(a, b, t)[:3, :3], expected, atol=1e-6)


def test_drift_between_corrected_keyframes_is_removed():
    """Tracking drifts 1 cm and 0.5 degree per frame; mapping puts keyframes 0 (frame 0) and 1 (frame 4) back on
    the true trajectory. Linear drift is then removed from the frames in between, not only from the keyframes."""
    truth = [pose(0.1 * k, 2.0 * k) for k in range(7)]
    tracked = [pose(0.1 * k + 0.01 * k, 2.5 * k) for k in range(7)]
    traj = TrackedTrajectory()
    for k in range(7):
        traj.record(k, 0.1 * k, tracked[k], 0.0, None, keyframe=k in (0, 4))
    assert traj.keyframe_records == {0: 0, 1: 4}
    traj.refine({0: truth[0], 1: truth[4]})  # mapping's corrections
    records, keyframe_pose = traj.records, traj.keyframe_poses
    poses = list(traj.poses())
    for k in range(5):
        rigid = keyframe_pose[records[k].reference] @ records[k].relative  # moved with its own keyframe only
        error = np.linalg.norm(poses[k][:3, 3] - truth[k][:3, 3])
        # (not zero: a world-frame correction of the heading also swings the position a little)
        assert error < 0.004 and error <= 0.3 * np.linalg.norm(rigid[:3, 3] - truth[k][:3, 3]) + 1e-9, k
        assert rotation_angle_deg(poses[k][:3, :3].T @ truth[k][:3, :3]) < 0.01, k
    # After the newest keyframe there is nothing to blend with: those frames move with it rigidly.
    assert np.allclose(poses[5], truth[4] @ np.linalg.inv(tracked[4]) @ tracked[5])


def test_poses_are_recomputed_only_where_keyframes_moved_and_equal_frame_pose():
    """poses() caches: after refinements and new frames in any order it equals frame_pose of every record."""
    from eslam_core.trajectory import TrackedTrajectory

    rng = np.random.default_rng(0)
    traj = TrackedTrajectory()

    def noisy(k):
        pose = np.eye(4)
        pose[:3, :3] = rotvec_to_matrix(rng.normal(size=3) * 0.05)
        pose[:3, 3] = [0.01 * k, 0.0, 0.0] + rng.normal(size=3) * 0.01
        return pose

    for k in range(40):
        traj.record(k, k / 30, noisy(k), 0.0, None, keyframe=k % 4 == 0)
        if k % 7 == 3:  # mapping refines the newest keyframes, sometimes before the next frame comes
            traj.refine({traj.keyframes - 1: noisy(k), max(traj.keyframes - 2, 0): noisy(k)})
        if k % 5 == 0:
            cached = traj.poses()
            np.testing.assert_array_equal(cached, np.stack([traj.pose(i) for i in range(len(traj))]))
        if k % 3 == 1:  # a thinned path (the node's) leaves the other frames uncached, and still equals frame_pose
            picked = thinned(len(traj), 8)
            np.testing.assert_array_equal(traj.poses(8), np.stack([traj.pose(int(i)) for i in picked]))
            np.testing.assert_array_equal(traj.timestamps(8), traj.timestamps()[picked])
    before = traj.poses()
    traj.refine({3: noisy(12)})
    after = traj.poses()
    moved = np.flatnonzero(np.abs(after - before).max(axis=(1, 2)) > 0)
    assert set(traj.records[k].reference for k in moved) == {2, 3}  # keyframe 3's frames, and those blending into it
    np.testing.assert_array_equal(after, np.stack([traj.pose(i) for i in range(len(traj))]))


def test_a_thinned_path_is_bounded_spread_and_stable():
    """At most max_poses, the first and the newest frame always, every s-th frame between; a frame shown stays
    shown as the run grows until the stride doubles."""
    assert list(thinned(5, None)) == list(thinned(5, 10)) == [0, 1, 2, 3, 4]
    previous = None
    for n in range(11, 3000, 7):
        picked = thinned(n, 100)
        assert min(n, 50) <= len(picked) <= 100 and picked[0] == 0 and picked[-1] == n - 1
        stride = picked[1] - picked[0]
        assert (np.diff(picked[:-1]) == stride).all() and stride & (stride - 1) == 0  # a power of two
        if previous is not None and previous[1] == stride:  # same stride: the earlier frames shown stay shown
            assert set(previous[0][:-1]) <= set(picked)
        previous = (picked, stride)


def test_a_frame_costs_under_650_bytes_and_survives_a_checkpoint():
    """Hours at 30 Hz keep every frame in the caller's process (and the essentials in the tracking process): 1.2 KB a
    frame as objects with three 4x4 arrays each, ~800 bytes as float64 columns; 600 with float32 poses (the cached
    pose and the keyframe poses included, a keyframe every 4th frame), 250 with the tracker's essential columns."""
    import tracemalloc

    def fill(traj: TrackedTrajectory, n: int) -> float:
        tracemalloc.start()
        before = tracemalloc.get_traced_memory()[0]
        for k in range(n):
            traj.record(k, k / 30, pose(0.01 * k, 0.1 * k), 0.1, pose(0.01 * k, 0.0) if k % 3 else None,
                        keyframe=k % 4 == 0, quality=0.5 + (k % 2) / 2, lost=k % 5 == 0, degraded=k % 7 == 0,
                        covariance=np.eye(6) * k if k % 2 else None)
        traj.poses()
        per_frame = (tracemalloc.get_traced_memory()[0] - before) / n
        tracemalloc.stop()
        return per_frame

    n = 16384  # a whole capacity: no half-filled growth in the figure
    traj, essential = TrackedTrajectory(), TrackedTrajectory(essential=True)
    full_bytes = fill(traj, n)
    assert full_bytes < 650, full_bytes
    essential_bytes = fill(essential, n) - 129  # (less the cache of poses(), which a tracker never asks for)
    assert essential_bytes < 280, essential_bytes
    np.testing.assert_allclose(essential.poses(), traj.poses(), atol=1e-6)
    assert essential.records[5].covariance is None and traj.records[5].covariance is not None

    traj.refine({7: pose(0.3, 1.0)})
    again = TrackedTrajectory.from_state_dict(traj.state_dict())
    np.testing.assert_array_equal(again.poses(), traj.poses())
    np.testing.assert_array_equal(again.timestamps(), traj.timestamps())
    for k in (0, 1, 5, n - 1):
        a, b = again.records[k], traj.records[k]
        assert (a.index, a.reference, a.quality, a.lost, a.degraded) == (b.index, b.reference, b.quality, b.lost,
                                                                          b.degraded)
        assert (a.covariance is None) == (k % 2 == 0) and (a.covariance is None or np.array_equal(a.covariance,
                                                                                                  b.covariance))
        assert (a.gt_pose is None) == (k % 3 == 0) and (a.gt_pose is None or np.array_equal(a.gt_pose, b.gt_pose))
    again.record(n, n / 30, pose(0.0, 0.0), 0.1, None, keyframe=True)  # and it goes on growing
    assert len(again) == n + 1 and again.keyframes == traj.keyframes + 1
