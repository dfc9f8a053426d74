"""Camera trajectory metrics: ATE and RPE (Sturm et al., IROS 2012), as reported by NICE-SLAM and ESLAM.

- ATE (absolute trajectory error): the estimated camera positions are rigidly aligned to the ground truth (Horn /
  Umeyama: rotation + translation, no scale), then the per-frame position errors are summarised (RMSE, mean, ...).
- RPE (relative pose error): the error of the motion between two poses `delta` apart (in frames, or ~`delta`
  metres along the ground-truth path); it measures drift and needs no alignment.

Everything here is in metres and radians internally; reports convert to cm and degrees.
The trajectories compared are `eslam_core.trajectory.Trajectory`s, read from TUM files by `datasets/tum.py`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eslam_core.datasets.tum import associate_timestamps
from eslam_core.trajectory import Trajectory, TrajectoryError


def rotation_angle(rotation: np.ndarray) -> np.ndarray:
    """Angle (radians) of rotation matrices (..., 3, 3).

    atan2 of the sine and cosine parts instead of arccos of the trace: arccos loses all precision for small angles,
    which are exactly the ones RPE measures.
    """
    r = np.asarray(rotation, dtype=np.float64)
    cos = (np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0
    axis_sin = np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1)
    sin = 0.5 * np.linalg.norm(axis_sin, axis=-1)
    return np.arctan2(sin, cos)


# ---------------------------------------------------------------------------------------------------------------
# Association and alignment


def associate(t_a: np.ndarray, t_b: np.ndarray, max_dt: float) -> np.ndarray:
    """Index pairs (M, 2) matching timestamps of `t_a` to `t_b`, one-to-one, |dt| <= max_dt, ordered by `t_a`.

    The pairing is `eslam_core.datasets.tum.associate_timestamps` (TUM's associate.py rule: closest first, each
    timestamp used once); here no pair at all is an error, since nothing could be compared.
    """
    if max_dt < 0:
        raise TrajectoryError(f"max_dt must be >= 0 seconds, got {max_dt}")
    t_a = np.asarray(t_a, dtype=np.float64)
    t_b = np.asarray(t_b, dtype=np.float64)
    pairs = associate_timestamps(t_a, t_b, max_dt)
    if not len(pairs):
        span = lambda t: f"[{t.min():.3f}, {t.max():.3f}]" if len(t) else "[empty]"  # noqa: E731
        raise TrajectoryError(
            f"no overlapping timestamps within {max_dt} s: the first trajectory spans {span(t_a)}, the second "
            f"{span(t_b)}; check that both use the same clock and data set (or raise max_dt)"
        )
    return pairs


def umeyama_alignment(
    src: np.ndarray, dst: np.ndarray, with_scale: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares (R, t, s) minimising sum |dst - (s R src + t)|^2 (Umeyama 1991).

    R is a proper rotation (det = +1) even when the best orthogonal fit would be a reflection; s = 1 unless
    `with_scale` (monocular methods need scale, RGB-D ones must not get it).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise TrajectoryError(f"alignment needs two (N, 3) point sets of equal shape, got {src.shape} and {dst.shape}")
    if len(src) < 3:
        raise TrajectoryError(f"alignment needs at least 3 point pairs to fix a rotation, got {len(src)}")
    if not (np.isfinite(src).all() and np.isfinite(dst).all()):
        raise TrajectoryError("alignment input contains nan/inf points")
    mean_src, mean_dst = src.mean(axis=0), dst.mean(axis=0)
    centred_src, centred_dst = src - mean_src, dst - mean_dst
    covariance = centred_dst.T @ centred_src / len(src)
    u, singular, vt = np.linalg.svd(covariance)
    reflection = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        reflection[2, 2] = -1.0
    rotation = u @ reflection @ vt
    scale = 1.0
    if with_scale:
        variance_src = (centred_src**2).sum() / len(src)
        if variance_src <= 0:
            raise TrajectoryError("cannot fit a scale: all source points coincide")
        scale = float(np.trace(np.diag(singular) @ reflection) / variance_src)
    translation = mean_dst - scale * rotation @ mean_src
    return rotation, translation, scale


# ---------------------------------------------------------------------------------------------------------------
# ATE


@dataclass(frozen=True, eq=False)
class AteResult:
    rmse: float  # metres
    mean: float
    median: float
    max: float
    std: float
    n: int  # matched poses
    errors: np.ndarray  # (n,) position error per matched pose, metres
    timestamps: np.ndarray  # (n,) ground-truth timestamps of the matched poses
    aligned_positions: np.ndarray  # (n, 3) estimated positions after alignment
    gt_positions: np.ndarray  # (n, 3)
    transform: np.ndarray  # 4x4 similarity applied to the estimate (identity without alignment)


def ate(est: Trajectory, gt: Trajectory, max_dt: float = 0.02, align: bool = True) -> AteResult:
    """Absolute trajectory error of the matched camera positions (metres), after rigid alignment when `align`."""
    pairs = associate(est.timestamps, gt.timestamps, max_dt)
    est_positions = est.positions[pairs[:, 0]]
    gt_positions = gt.positions[pairs[:, 1]]
    transform = np.eye(4)
    if align:
        rotation, translation, scale = umeyama_alignment(est_positions, gt_positions)
        transform[:3, :3] = scale * rotation
        transform[:3, 3] = translation
    aligned = est_positions @ transform[:3, :3].T + transform[:3, 3]
    errors = np.linalg.norm(aligned - gt_positions, axis=1)
    return AteResult(
        rmse=float(np.sqrt(np.mean(errors**2))),
        mean=float(errors.mean()),
        median=float(np.median(errors)),
        max=float(errors.max()),
        std=float(errors.std()),
        n=len(errors),
        errors=errors,
        timestamps=gt.timestamps[pairs[:, 1]],
        aligned_positions=aligned,
        gt_positions=gt_positions,
        transform=transform,
    )


def still_camera_ate(positions: np.ndarray) -> float:
    """The ATE RMSE (metres) of a camera that never moved, against the true `positions` (n, 3): after the best
    rigid alignment its one position lands on their centroid. An accuracy bound on a path must be well below this,
    or a tracker that returns a constant pose passes it."""
    positions = np.asarray(positions, dtype=np.float64)
    return float(np.sqrt(np.mean(np.sum((positions - positions.mean(axis=0)) ** 2, axis=1))))


# ---------------------------------------------------------------------------------------------------------------
# RPE


@dataclass(frozen=True, eq=False)
class RpeResult:
    delta: float  # pose distance of each pair, in `unit`
    unit: str  # "frames" or "metres"
    n: int  # pose pairs
    trans_rmse: float  # metres
    trans_mean: float
    rot_rmse: float  # degrees
    rot_mean: float
    trans_errors: np.ndarray  # (n,) metres
    rot_errors: np.ndarray  # (n,) degrees


def path_length(positions: np.ndarray) -> np.ndarray:
    """Cumulative distance travelled (N,), starting at 0."""
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def _rpe_pairs(gt_positions: np.ndarray, delta: float, unit: str) -> tuple[np.ndarray, np.ndarray]:
    n = len(gt_positions)
    if unit == "frames":
        if delta < 1 or int(delta) != delta:
            raise TrajectoryError(f"RPE delta in frames must be a positive integer, got {delta}")
        first = np.arange(max(n - int(delta), 0))
        return first, first + int(delta)
    if unit == "metres":
        if not delta > 0:
            raise TrajectoryError(f"RPE delta in metres must be positive, got {delta}")
        travelled = path_length(gt_positions)
        # Pair each pose with the first later pose at least `delta` metres further along the ground-truth path.
        # A nanometre of slack keeps sums of evenly spaced steps (0.1 m x 10) from missing their pose by rounding.
        second = np.maximum(np.searchsorted(travelled, travelled + delta - 1e-9, side="left"), np.arange(n) + 1)
        first = np.flatnonzero(second < n)
        return first, second[first]
    raise TrajectoryError(f"RPE unit must be 'frames' or 'metres', got {unit!r}")


def rpe(est: Trajectory, gt: Trajectory, delta: float = 1, unit: str = "frames", max_dt: float = 0.02) -> RpeResult:
    """Relative pose error over pose pairs `delta` frames apart, or ~`delta` metres apart along the ground truth.

    Error of a pair (i, j): E = (G_i^-1 G_j)^-1 (P_i^-1 P_j); translation error |t(E)| in metres, rotation error
    angle(R(E)) in degrees. Invariant to any rigid transform of either trajectory, so no alignment is needed.
    """
    pairs = associate(est.timestamps, gt.timestamps, max_dt)
    est_poses = est.poses[pairs[:, 0]]
    gt_poses = gt.poses[pairs[:, 1]]
    i, j = _rpe_pairs(gt_poses[:, :3, 3], delta, unit)
    if i.size == 0:
        length = path_length(gt_poses[:, :3, 3])[-1]
        raise TrajectoryError(
            f"no pose pairs {delta} {unit} apart: the {len(gt_poses)} matched poses span {length:.2f} m of "
            "ground-truth path; use a smaller RPE delta"
        )
    gt_motion = np.linalg.inv(gt_poses[i]) @ gt_poses[j]
    est_motion = np.linalg.inv(est_poses[i]) @ est_poses[j]
    error = np.linalg.inv(gt_motion) @ est_motion
    trans_errors = np.linalg.norm(error[:, :3, 3], axis=1)
    rot_errors = np.degrees(rotation_angle(error[:, :3, :3]))
    return RpeResult(
        delta=float(delta),
        unit=unit,
        n=int(i.size),
        trans_rmse=float(np.sqrt(np.mean(trans_errors**2))),
        trans_mean=float(trans_errors.mean()),
        rot_rmse=float(np.sqrt(np.mean(rot_errors**2))),
        rot_mean=float(rot_errors.mean()),
        trans_errors=trans_errors,
        rot_errors=rot_errors,
    )
