"""Rigid-body math on torch tensors: quaternions (w, x, y, z), pose parameters, camera rays.

ESLAM optimises a camera pose as a translation and a quaternion with Adam, no manifold operations (paper Sec. 3.4).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial.transform import Rotation


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) quaternion (w, x, y, z), not necessarily unit -> (..., 3, 3) rotation."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def matrix_to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation -> (..., 4) unit quaternion (w, x, y, z) with w >= 0 (numerically stable branch choice)."""
    m = R.reshape(-1, 3, 3)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    # Four candidate formulas; each is accurate when its denominator is large, so take the largest.
    cands = torch.stack(
        [
            torch.stack([1 + tr, m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]], -1),
            torch.stack([m[:, 2, 1] - m[:, 1, 2], 1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
                         m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0]], -1),
            torch.stack([m[:, 0, 2] - m[:, 2, 0], m[:, 0, 1] + m[:, 1, 0],
                         1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2], m[:, 1, 2] + m[:, 2, 1]], -1),
            torch.stack([m[:, 1, 0] - m[:, 0, 1], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1],
                         1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]], -1),
        ],
        dim=1,
    )
    diag = torch.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], -1)
    best = diag.argmax(-1)
    q = cands[torch.arange(len(m), device=m.device), best]
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[:, :1] < 0, -q, q)
    return q.reshape(R.shape[:-2] + (4,))


def quaternion_xyzw_to_matrix(q) -> np.ndarray:
    """numpy (..., 4) quaternion in the (x, y, z, w) order of TUM files and ROS messages -> (..., 3, 3) rotation."""
    q = torch.as_tensor(np.asarray(q, dtype=np.float64))
    return quaternion_to_matrix(q[..., [3, 0, 1, 2]]).numpy()


def matrix_to_quaternion_xyzw(R) -> np.ndarray:
    """numpy (..., 3, 3) rotation -> (..., 4) unit quaternion (x, y, z, w) with w >= 0. SciPy's conversion: through
    torch, the per-operation overhead made one matrix cost 0.23 ms (the ROS node converts three per pose), SciPy's
    0.05 ms."""
    R = np.asarray(R, dtype=np.float64)
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat(canonical=True)
    return q.reshape(R.shape[:-2] + (4,))


def pose_to_params(T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., 4, 4) camera-to-world -> translation (..., 3), quaternion (..., 4)."""
    return T[..., :3, 3].clone(), matrix_to_quaternion(T[..., :3, :3])


def params_to_pose(t: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Translation (..., 3) and quaternion (..., 4) -> (..., 4, 4) camera-to-world (differentiable)."""
    R = quaternion_to_matrix(q)
    top = torch.cat([R, t.unsqueeze(-1)], dim=-1)
    bottom = torch.zeros(top.shape[:-2] + (1, 4), dtype=top.dtype, device=top.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], dim=-2)


def pixel_directions(u: torch.Tensor, v: torch.Tensor, fx: float, fy: float, cx: float, cy: float) -> torch.Tensor:
    """Camera-frame ray directions with unit z, so that a point at planar depth z is `z * direction`."""
    return torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], dim=-1)


def rays_to_world(dirs_cam: torch.Tensor, c2w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Origins and directions in the world for (N,3) camera directions and (N,4,4) or (4,4) poses."""
    if c2w.dim() == 2:
        return c2w[:3, 3].expand(len(dirs_cam), 3), dirs_cam @ c2w[:3, :3].T
    return c2w[:, :3, 3], torch.einsum("nij,nj->ni", c2w[:, :3, :3], dirs_cam)


def depth_points_world(dirs_cam: torch.Tensor, depth: torch.Tensor, c2w: torch.Tensor) -> torch.Tensor:
    """World points (N, 3) of pixels with camera directions (N, 3) (unit z) and planar depths (N,), camera `c2w`."""
    return dirs_cam * depth[:, None] @ c2w[:3, :3].T + c2w[:3, 3]


def skew(v) -> np.ndarray:
    """[v]x (numpy): skew(v) @ a = v x a."""
    x, y, z = np.asarray(v, dtype=np.float64)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rotvec_to_matrix(rotvec) -> np.ndarray:
    """Rodrigues' formula (numpy): the rotation matrix of a rotation vector (axis * angle in radians)."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-12:
        return np.eye(3)
    K = skew(rotvec / angle)
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula (torch, on w's device): the rotation matrix of the rotation vector w."""
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    K = torch.linalg.cross(eye, w.expand(3, 3))  # row i: e_i x w, so K v = w x v
    theta = float(w.norm())
    if theta < 1e-4:  # the series of sin(t) / t and (1 - cos(t)) / t^2: exact to float64 there
        a, b = 1.0 - theta**2 / 6.0, 0.5 - theta**2 / 24.0
    else:
        a, b = math.sin(theta) / theta, (1.0 - math.cos(theta)) / theta**2
    return eye + a * K + b * (K @ K)


def scale_motion(M: np.ndarray, factor: float) -> np.ndarray:
    """A rigid motion repeated `factor` times (rotation angle and translation scaled): velocity x time.
    (Rodrigues' formula in numpy: scipy's Rotation costs ~20x more, and a trajectory calls this once per frame.)"""
    out = np.eye(4)
    out[:3, 3] = M[:3, 3] * factor
    out[:3, :3] = rotvec_to_matrix(matrix_to_rotvec(M[:3, :3]) * factor)
    return out


def matrix_to_rotvec(R) -> np.ndarray:
    """The rotation vector (axis * angle in radians) of a rotation matrix: the inverse of rotvec_to_matrix."""
    R = np.asarray(R, dtype=np.float64)
    angle = float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
    if angle < 1e-9:
        return np.zeros(3)
    if angle > np.pi - 1e-3:  # the axis is ill-defined from the skew part near a half turn
        from scipy.spatial.transform import Rotation

        return Rotation.from_matrix(R).as_rotvec()
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2 * np.sin(angle))
    return axis * angle


def interpolate_pose(a: np.ndarray, b: np.ndarray, t: float) -> np.ndarray:
    """The pose a fraction `t` of the way from `a` to `b`: translation linear, rotation along the geodesic."""
    return a @ scale_motion(relative_motion(a, b), t)


def relative_motion(T_prev: np.ndarray, T_cur: np.ndarray) -> np.ndarray:
    """Motion from the previous to the current camera, expressed in the previous camera's frame."""
    return np.linalg.inv(T_prev) @ T_cur


def rotation_angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def orthonormalize(T):
    """The rigid transform nearest to a 4x4 pose whose rotation drifted from orthonormal (float rounding over many
    composed updates, float32 optimiser output): the rotation's polar factor by SVD, the translation kept.
    numpy or torch in, the same out; (..., 4, 4) for many poses."""
    if isinstance(T, torch.Tensor):
        return torch.from_numpy(orthonormalize(T.detach().double().numpy())).to(T.dtype)
    T = np.array(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[..., :3, :3])
    reflection = np.linalg.det(U @ Vt) < 0  # a reflection is not a rotation: flip the weakest axis
    U[..., :, -1] *= np.where(reflection, -1.0, 1.0)[..., None]
    T[..., :3, :3] = U @ Vt
    T[..., 3, :] = (0.0, 0.0, 0.0, 1.0)
    return T
