"""Fast tracking: Gauss-Newton alignment of the frame's back-projected depth to the map's SDF.

An alternative to the paper's tracker for live use on a CPU (`tracking.method: sdf`, the `fast` preset). Each pixel
with depth gives a point p in the camera; for the pose (R, t) its residual is the map's signed distance at the
world point, r = T * phi_g(R p + t) (metres). Only points inside the truncation band carry a gradient. With a left
perturbation x -> x + w x x + v, dr/dv = T grad(phi), dr/dw = T (x cross grad(phi)); a damped Gauss-Newton step with
Huber weights solves for (v, w). One SDF query and its gradient per point and iteration, instead of rendering ~40
samples per ray: roughly 10-50x cheaper per iteration, at the cost of ignoring colour.
"""
from __future__ import annotations

import numpy as np
import torch

from .config import Config
from .field import SceneField
from .frames import PreparedFrame, border_mask
from .tracking import TrackingResult, frozen


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of the rotation vector w (Rodrigues)."""
    theta = w.norm()
    K = torch.zeros(3, 3, dtype=w.dtype)
    K[0, 1], K[0, 2], K[1, 0], K[1, 2], K[2, 0], K[2, 1] = -w[2], w[1], w[2], -w[0], -w[1], w[0]
    if theta < 1e-9:
        return torch.eye(3, dtype=w.dtype) + K
    return torch.eye(3, dtype=w.dtype) + torch.sin(theta) / theta * K + (1 - torch.cos(theta)) / theta**2 * K @ K


def huber_weights(r: torch.Tensor, k: float) -> torch.Tensor:
    a = r.abs()
    return torch.where(a <= k, torch.ones_like(a), k / a)


def sdf_residuals(field: SceneField, points_world: torch.Tensor, truncation: float
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Residuals T * phi_g(x) (metres) and their gradients with respect to x."""
    x = points_world.detach().requires_grad_(True)
    r = field.sdf(x) * truncation
    (grad,) = torch.autograd.grad(r.sum(), x)
    return r.detach(), grad


def gauss_newton_step(points_world: torch.Tensor, r: torch.Tensor, grad: torch.Tensor, w: torch.Tensor,
                      damping: float) -> torch.Tensor:
    """(v, w) minimising sum w_i (r_i + J_i [v; w])^2 + damping |.|^2, J_i = [grad_i, x_i x grad_i]."""
    J = torch.cat([grad, torch.cross(points_world, grad, dim=-1)], dim=-1).double()
    Jw = J * w.double()[:, None]
    H = Jw.T @ J
    b = Jw.T @ r.double()
    H = H + damping * torch.diag(torch.diagonal(H).clamp_min(1e-9))
    return -torch.linalg.solve(H, b)


class SDFTracker:
    def __init__(self, cfg: Config, dirs_cam: torch.Tensor, height: int, width: int):
        self.cfg = cfg
        self.dirs_cam = dirs_cam
        self.border = border_mask(height, width, cfg.tracking.border).reshape(-1)

    def track(self, field: SceneField, frame: PreparedFrame, init_pose: torch.Tensor,
              usable: torch.Tensor | None = None) -> TrackingResult:
        tc, T = self.cfg.tracking, self.cfg.model.truncation
        depth = frame.depth.reshape(-1)
        valid = self.border & (depth > 0)
        if usable is not None:
            valid &= usable.reshape(-1)
        candidates = torch.nonzero(valid).squeeze(1)
        if len(candidates) < 50 or tc.iterations == 0:
            return TrackingResult(init_pose.clone(), float("nan"), len(candidates))
        pix = candidates[torch.randperm(len(candidates))[: tc.rays]]
        p_cam = self.dirs_cam[pix] * depth[pix, None]
        R, t = init_pose[:3, :3].double(), init_pose[:3, 3].double()
        best_cost, best = float("inf"), init_pose.clone()
        with frozen(field):
            for it in range(tc.iterations + 1):  # the last pass only scores the final pose
                x = (p_cam.double() @ R.T + t).float()
                r, grad = sdf_residuals(field, x, T)
                inside = r.abs() < 0.99 * T  # saturated (free space / behind) points carry no gradient
                if inside.sum() < 30:
                    break
                w = huber_weights(r, tc.huber) * inside
                cost = float((w * r**2).sum() / w.sum())
                if cost < best_cost:
                    best_cost = cost
                    best = torch.eye(4)
                    best[:3, :3], best[:3, 3] = R.float(), t.float()
                if it == tc.iterations:
                    break
                delta = gauss_newton_step(x, r, grad, w, damping=1e-4)
                dR = so3_exp(delta[3:])
                R, t = dR @ R, dR @ t + delta[:3]
                if delta.norm() < 1e-6:
                    break
        return TrackingResult(best, best_cost, len(candidates))
