"""Fast tracking: Gauss-Newton alignment of the frame's back-projected depth to the map's SDF and colour.

An alternative to the paper's tracker for live use on a CPU (`tracking.method: sdf`, the `fast` preset). Each pixel
with depth gives a point p in the camera and the world point x = R p + t. Two residuals per point, each divided by
its robust scale so that both are unitless:
- geometric: the map's signed distance at x, T * phi_g(x) / huber (metres / metres);
- photometric: the map's colour at x against the pixel's, as grey levels, (g(phi_a(x)) - g(I(u))) / color_huber.
  Without it the SDF alone leaves directions in which the visible surfaces slide along themselves (a corridor, a
  ceiling seen at a grazing angle) and the constant-velocity prediction's error survives, frame after frame.
Both are queries of the map at x, so with a left perturbation x -> x + w x x + v the Jacobian row of a residual with
spatial gradient g is [g, x cross g]. Damped Gauss-Newton steps with Huber weights solve for (v, w). One SDF and
one colour query (with gradients) per point and iteration instead of rendering ~40 samples per ray.

Only points inside the truncation band (where the SDF has a gradient and the colour is the surface's) give residuals.
The cost that picks the best pose counts every point, a saturated one at the largest penalty; otherwise a pose that
pushed points out of the band would look good. Points on space no keyframe has seen are left out (see observed.py).
"""
from __future__ import annotations

import torch

from .config import Config
from .field import SceneField
from .frames import PreparedFrame, border_mask
from .observed import ObservedSpace
from .tracking import TrackingResult, frozen

GREY = torch.tensor([0.299, 0.587, 0.114])
SATURATED_COLOR = 3.0  # the photometric penalty of a saturated point, in units of color_huber


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of the rotation vector w (Rodrigues)."""
    theta = w.norm()
    K = torch.zeros(3, 3, dtype=w.dtype)
    K[0, 1], K[0, 2], K[1, 0], K[1, 2], K[2, 0], K[2, 1] = -w[2], w[1], w[2], -w[0], -w[1], w[0]
    if theta < 1e-9:
        return torch.eye(3, dtype=w.dtype) + K
    return torch.eye(3, dtype=w.dtype) + torch.sin(theta) / theta * K + (1 - torch.cos(theta)) / theta**2 * K @ K


def huber_weights(r: torch.Tensor) -> torch.Tensor:
    """IRLS weights of unitless residuals (Huber with threshold 1)."""
    return 1.0 / r.abs().clamp_min(1.0)


def huber_cost(r: torch.Tensor) -> torch.Tensor:
    """Huber's rho of unitless residuals: quadratic up to 1, linear beyond."""
    a = r.abs()
    return torch.where(a <= 1.0, 0.5 * a**2, a - 0.5)


def field_residuals(field: SceneField, x: torch.Tensor, truncation: float, with_color: bool
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """Signed distance T * phi_g(x) (metres) and grey level g(phi_a(x)), each with its gradient in x."""
    x = x.detach().requires_grad_(True)
    sdf = field.sdf(x) * truncation
    (sdf_grad,) = torch.autograd.grad(sdf.sum(), x)
    if not with_color:
        return sdf.detach(), sdf_grad, None, None
    grey = field.color(x) @ GREY
    (grey_grad,) = torch.autograd.grad(grey.sum(), x)
    return sdf.detach(), sdf_grad, grey.detach(), grey_grad


def gauss_newton_step(x: torch.Tensor, r: torch.Tensor, grad: torch.Tensor, w: torch.Tensor,
                      damping: float) -> torch.Tensor:
    """(v, w) minimising sum w_i (r_i + J_i [v; w])^2 + damping |.|^2, J_i = [grad_i, x_i x grad_i]."""
    J = torch.cat([grad, torch.cross(x, grad, dim=-1)], dim=-1).double()
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
              usable: torch.Tensor | None = None, observed: ObservedSpace | None = None) -> TrackingResult:
        tc, T = self.cfg.tracking, self.cfg.model.truncation
        depth = frame.depth.reshape(-1)
        valid = self.border & (depth > 0)
        if usable is not None:
            valid &= usable.reshape(-1)
        candidates = torch.nonzero(valid).squeeze(1)
        if len(candidates) < 50 or tc.iterations == 0:
            return TrackingResult(init_pose.clone(), float("nan"), len(candidates))
        pix = candidates[torch.randperm(len(candidates))[: tc.rays]]
        p_cam = (self.dirs_cam[pix] * depth[pix, None]).double()
        lam = tc.color_weight
        grey_pixel = frame.rgb.reshape(-1, 3)[pix] @ GREY if lam > 0 else None
        R, t = init_pose[:3, :3].double(), init_pose[:3, 3].double()
        used = None  # the points on observed surface at the initial pose; fixed, so that costs compare
        best_cost, best = float("inf"), init_pose.clone()
        with frozen(field):
            for it in range(tc.iterations + 1):  # the last pass only scores the final pose
                x = (p_cam @ R.T + t).float()
                sdf, sdf_grad, grey, grey_grad = field_residuals(field, x, T, lam > 0)
                if used is None:
                    used = observed.contains(x) if observed is not None else torch.ones(len(x), dtype=torch.bool)
                    if used.sum() < 30:
                        break
                band = used & (sdf.abs() < 0.99 * T)
                r_geo = sdf.clamp(-T, T) / tc.huber
                cost = huber_cost(r_geo)
                if lam > 0:
                    r_col = (grey - grey_pixel) / tc.color_huber
                    cost = cost + lam * torch.where(band, huber_cost(r_col), huber_cost(torch.tensor(SATURATED_COLOR)))
                cost = float(cost[used].mean())
                if cost < best_cost:
                    best_cost = cost
                    best = torch.eye(4)
                    best[:3, :3], best[:3, 3] = R.float(), t.float()
                if it == tc.iterations or band.sum() < 30:
                    break
                xb = x[band]
                r, g, w = r_geo[band], sdf_grad[band] / tc.huber, huber_weights(r_geo[band])
                if lam > 0:
                    rc = r_col[band]
                    xb = torch.cat([xb, xb])
                    r = torch.cat([r, rc])
                    g = torch.cat([g, grey_grad[band] / tc.color_huber])
                    w = torch.cat([w, lam * huber_weights(rc)])
                delta = gauss_newton_step(xb, r, g, w, damping=1e-4)
                dR = so3_exp(delta[3:])
                R, t = dR @ R, dR @ t + delta[:3]
                if delta.norm() < 1e-6:
                    break
        return TrackingResult(best, best_cost, len(candidates))
