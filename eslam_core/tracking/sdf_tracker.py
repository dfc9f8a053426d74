"""Fast tracking: Gauss-Newton alignment of the frame's back-projected depth to the map's SDF and to the images.

An alternative to the paper's tracker for live use on a CPU (`tracking.method: sdf`, the `fast` preset). Each pixel
with depth gives a point p in the camera and the world point x = R p + t. Residuals per point, each divided by its
robust scale so that all are unitless:
- geometric: the map's signed distance at x, T * phi_g(x) / huber (metres / metres);
- map colour (`color_weight`): the map's colour at x against the pixel's, as grey levels, (g(phi_a(x)) - g(I(u))) /
  color_huber;
- keyframe photometric (`photometric_weight`): the newest keyframe's grey level where x projects into it against
  the pixel's, aligned coarse to fine over an image pyramid (photometric.py).
The SDF alone leaves directions in which the visible surfaces slide along themselves (a corridor, a ceiling seen at
a grazing angle) and the constant-velocity prediction's error survives, frame after frame; the colour terms hold
them, the keyframe's sharp images better than the map's blurred colour. All residuals are functions of x, so with a
left perturbation x -> x + w x x + v the Jacobian row of a residual with spatial gradient g is [g, x cross g].
Gauss-Newton steps with Huber weights solve for (v, w) in the directions the frame constrains (information.py): one
SDF query (with gradients) per point and iteration instead of rendering ~40 samples per ray. Along a direction the
frame leaves free (a wall, a corridor) the pose keeps its start, or `free_prior` where one is given.

Only points inside the truncation band (where the SDF has a gradient and the colour is the surface's) give map
residuals. The cost that picks the best pose counts every point, a saturated one at the largest penalty; otherwise a
pose that pushed points out of the band (or out of the keyframe's view) would look good. Points on space no mapped
keyframe has seen are left out, and where enough of them lie on settled surface (mapped over several steps) only
those are aligned (see observed.py).

The alignment runs on the map's device, the small 6x6 systems included; the choice of the best pose and the stopping
tests read a few numbers back per iteration (six iterations per frame), the pose comes back once.
"""
from __future__ import annotations

import ctypes

import numpy as np
import torch

from eslam_core.camera import Intrinsics
from eslam_core.config import Config, SDFTrackerConfig, TrackingConfig
from eslam_core.cpu import denormals_flushed, flat_nonzero, one_thread
from eslam_core.representation.field import FoldedMap, FrozenField, SceneField
from eslam_core.frames import PreparedFrame, border_mask
from eslam_core.geometry import depth_points_world, matrix_to_rotvec, so3_exp
from eslam_core.mapping.extent import draw_in_extent
from eslam_core.mapping.keyframes import Keyframe
from eslam_core.mapping.observed import ObservedSurfaces
from eslam_core.native import load_kernel, pointer
from eslam_core.tracking.information import constrained_step, pose_covariance, unconstrained_part
from eslam_core.tracking.photometric import Reference, grey_pyramid, photometric_residuals, sample, to_grey
from eslam_core.tracking.result import TrackingResult

SATURATED_COLOR = 3.0  # the colour penalty of a saturated point, in units of its Huber scale
SATURATED_COST = SATURATED_COLOR - 0.5  # its Huber cost (huber_cost of SATURATED_COLOR)


def huber_weights(r: torch.Tensor) -> torch.Tensor:
    """IRLS weights of unitless residuals (Huber with threshold 1)."""
    return 1.0 / r.abs().clamp_min(1.0)


def huber_cost(r: torch.Tensor) -> torch.Tensor:
    """Huber's rho of unitless residuals: quadratic up to 1, linear beyond."""
    a = r.abs()
    return torch.where(a <= 1.0, 0.5 * a**2, a - 0.5)


def field_residuals(field: FrozenField, x: torch.Tensor, truncation: float, with_color: bool,
                    gradients: bool = True
                    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None, torch.Tensor | None]:
    """Signed distance T * phi_g(x) (metres) and grey level g(phi_a(x)), each with its gradient in x (None without
    `gradients`)."""
    if not gradients:
        with torch.no_grad():
            return field.sdf(x) * truncation, None, to_grey(field.color(x)) if with_color else None, None
    sdf, sdf_grad = field.sdf_with_gradient(x)
    if not with_color:
        return sdf * truncation, sdf_grad * truncation, None, None
    x = x.detach().requires_grad_(True)
    grey = to_grey(field.color(x))
    (grey_grad,) = torch.autograd.grad(grey.sum(), x)
    return sdf * truncation, sdf_grad * truncation, grey.detach(), grey_grad


def normal_equations(x: torch.Tensor, r: torch.Tensor, grad: torch.Tensor, w: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """H = sum w_i J_i^T J_i and b = sum w_i J_i^T r_i (double), J_i = [grad_i, x_i x grad_i]: one residual
    term's share of a Gauss-Newton step. On CPU tensors one pass of the C kernel (kernels/gauss_newton.c)."""
    x, r, grad, w = x.double(), r.double(), grad.double(), w.double()
    lib = load_kernel("gauss_newton") if x.device.type == "cpu" else None
    if lib is not None:
        x, r, grad, w = x.contiguous(), r.contiguous(), grad.contiguous(), w.contiguous()
        H, b = torch.empty(6, 6, dtype=torch.float64), torch.empty(6, dtype=torch.float64)
        lib.normal_equations(pointer(x), pointer(r), pointer(grad), pointer(w), ctypes.c_int64(len(x)), pointer(H),
                             pointer(b))
        return H, b
    # As in the kernel, rows of weight 0 take no part even where their residual or gradient is not finite.
    used = w > 0
    J = torch.where(used[:, None], torch.cat([grad, torch.cross(x, grad, dim=-1)], dim=-1), 0.0)
    Jw = J * w[:, None]
    return Jw.T @ J, Jw.T @ torch.where(used, r, 0.0)


def pose_change(R: torch.Tensor, t: torch.Tensor, target: torch.Tensor) -> np.ndarray:
    """(v, w) of the left perturbation that takes the pose (R, t) to `target` (4x4): target = exp(w) (R, t) + v."""
    target = target.double().cpu().numpy()
    dR = target[:3, :3] @ R.cpu().numpy().T
    return np.concatenate([target[:3, 3] - dR @ t.cpu().numpy(), matrix_to_rotvec(dR)])


def pyramid_level(iteration: int, iterations: int, levels: int) -> int:
    """Coarse to fine: the iterations are split evenly over the levels, the coarsest first."""
    return min(levels - 1, levels * (iterations - 1 - iteration) // max(iterations, 1))


class SDFTracker:
    def __init__(self, tracking: TrackingConfig, settings: SDFTrackerConfig, truncation: float, dirs_cam: torch.Tensor,
                 intr: Intrinsics):
        self.tracking, self.settings, self.truncation = tracking, settings, truncation
        self.dirs_cam = dirs_cam
        self.intr = intr
        self.border = border_mask(intr.height, intr.width, tracking.border).reshape(-1)
        self.border_pixels = max(int(self.border.sum()), 1)
        self._reference: Reference | None = None
        self._folded = FoldedMap()

    @staticmethod
    def of(cfg: Config, dirs_cam: torch.Tensor, intr: Intrinsics) -> "SDFTracker":
        """The tracker of `cfg`'s sections."""
        return SDFTracker(cfg.tracking, cfg.sdf_tracker, cfg.model.truncation, dirs_cam, intr)

    def _on(self, device: torch.device) -> None:
        """Keep the per-camera tables on the map's device (moved once)."""
        if self.dirs_cam.device != device:
            self.dirs_cam, self.border = self.dirs_cam.to(device), self.border.to(device)

    def reference(self, keyframe: Keyframe | None, device: torch.device = torch.device("cpu")) -> Reference | None:
        """The keyframe (host memory) prepared for photometric alignment on `device`, rebuilt only when the keyframe
        changes (its pose is read every time: mapping refines it)."""
        if keyframe is None or keyframe.rgb.numel() == 0 or self.settings.photometric_weight == 0:
            return None
        ref = self._reference
        if ref is None or ref.frame_index != keyframe.frame_index or ref.depth.device != device:
            ref = Reference.build(keyframe.frame_index, keyframe.rgb.to(device).float() / 255.0,
                                  keyframe.depth_image().to(device), keyframe.pose.to(device),
                                  self.settings.pyramid_levels)
            self._reference = ref
        ref.pose = keyframe.pose.double().to(device)
        return ref

    @one_thread()  # see cpu.py (a GPU's work is not split by these threads either)
    @denormals_flushed()
    def track(self, field: SceneField, frame: PreparedFrame, init_pose: torch.Tensor,
              extent: np.ndarray | None = None, observed: ObservedSurfaces | None = None,
              keyframe: Keyframe | None = None, map_version: int | None = None,
              free_prior: torch.Tensor | None = None) -> TrackingResult:
        """Align the frame's depth points inside `extent` (the map's, at the starting pose) to the map (SDF and,
        with `color_weight`, the map's colour) and, with `photometric_weight`, to the images of `keyframe`
        (normally the newest keyframe). `map_version`: changes whenever the field's values do (None: unknown).
        `free_prior`: the pose to keep along the directions the frame does not constrain (information.py), where
        that is not `init_pose` (None: keep the start's). Inputs and the result are host tensors; the work runs on
        the field's device."""
        tc, sc, T = self.tracking, self.settings, self.truncation
        device = field.device
        self._on(device)
        image, depth = frame.rgb.to(device), frame.depth.to(device).reshape(-1)
        start = init_pose.to(device)
        candidates = flat_nonzero(self.border & (depth > 0))
        pix, inside = draw_in_extent(candidates, min(tc.rays, len(candidates)), lambda pix: depth_points_world(
            self.dirs_cam[pix], depth[pix], start), extent)
        depth_fraction = len(candidates) * inside / self.border_pixels
        if len(pix) < 50 or tc.iterations == 0:
            return TrackingResult(init_pose.clone(), float("nan"), len(pix), depth_fraction, mapped_fraction=inside)
        p_cam = (self.dirs_cam[pix] * depth[pix, None]).double()
        median_depth = float(p_cam[:, 2].median())  # (the scale of a turn: information.py)
        lam = sc.color_weight
        grey_pixel = to_grey(image.reshape(-1, 3)[pix]) if lam > 0 else None
        ref = self.reference(keyframe, device)
        if ref is not None:
            u, v = (pix % self.intr.width).float(), (pix // self.intr.width).float()
            grey_current = [sample(level[None, None], u, v, 2.0**i)[:, 0].double()
                            for i, level in enumerate(grey_pyramid(image, len(ref.levels)))]
        R, t = start[:3, :3].double(), start[:3, 3].double()
        used = photo_used = seen = None  # the points scored, fixed at the initial pose so that costs compare
        best_cost, best_Rt, inliers = float("inf"), None, 0.0
        normal, at_best = None, None  # the last normal equations (H, chi2, residuals), and those at the best pose
        fixed = self._folded.of(field, map_version)  # the map does not change while tracking
        for it in range(tc.iterations + 1):  # the last pass only scores the final pose
            x = p_cam @ R.T + t
            last = it == tc.iterations
            sdf, sdf_grad, grey, grey_grad = field_residuals(fixed, x.float(), T, lam > 0, gradients=not last)
            level = pyramid_level(it, tc.iterations, len(ref.levels)) if ref is not None and not last else 0
            # Poses of the coarse image levels are not candidates for the best one (saves the full-resolution
            # photometric residuals there): the first (the prediction), the fine ones and the final one are.
            scored = it == 0 or level == 0
            if used is None:
                used, seen = observed.alignable(x.float()) if observed is not None else \
                    (torch.ones(len(x), dtype=torch.bool, device=device),) * 2
                if used.sum() < 30:
                    break
            band = used & (sdf.abs() < 0.99 * T)
            r_geo = sdf.clamp(-T, T) / sc.huber
            cost = huber_cost(r_geo)
            if lam > 0:
                r_col = (grey - grey_pixel) / sc.color_huber
                cost = cost + lam * torch.where(band, huber_cost(r_col), SATURATED_COST)
            cost = float(cost[used].mean())
            if ref is not None and scored:
                r_ph, g_ph, ok = photometric_residuals(x, grey_current[0], ref, 0, self.intr, T)
                if photo_used is None:
                    photo_used = ok
                if photo_used.any():
                    r_ph = r_ph / sc.photometric_huber
                    photo_cost = torch.where(ok, huber_cost(r_ph), SATURATED_COST)
                    cost += sc.photometric_weight * float(photo_cost[photo_used].mean())
            better = scored and cost < best_cost
            if better:
                best_cost, inliers = cost, float(band.sum()) / max(float(used.sum()), 1.0)
                best_Rt, at_best = (R, t), normal  # (the final pass has none of its own: the last step's)
            if last or band.sum() < 30:
                break
            # Points outside a term's mask take part with weight 0 (cheaper than gathering the others).
            w_geo = huber_weights(r_geo) * band
            H, b = normal_equations(x, r_geo, sdf_grad / sc.huber, w_geo)
            chi2, residuals = w_geo @ r_geo**2, band.sum()
            if lam > 0:
                w_col = lam * huber_weights(r_col) * band
                Hc, bc = normal_equations(x, r_col, grey_grad / sc.color_huber, w_col)
                H, b, chi2, residuals = H + Hc, b + bc, chi2 + w_col @ r_col**2, residuals + band.sum()
            if ref is not None and photo_used.any():
                if level > 0:
                    r_ph, g_ph, ok = photometric_residuals(x, grey_current[level], ref, level, self.intr, T)
                    r_ph = r_ph / sc.photometric_huber
                w_ph = sc.photometric_weight * huber_weights(r_ph) * (ok & photo_used)
                Hp, bp = normal_equations(x, r_ph, g_ph / sc.photometric_huber, w_ph)
                H, b = H + Hp, b + bp
                chi2, residuals = chi2 + w_ph.double() @ r_ph**2, residuals + (w_ph > 0).sum()
            normal = (H.cpu().numpy(), float(chi2), int(residuals))
            if better:
                at_best = normal
            if it == 0 and free_prior is not None:
                shift = unconstrained_part(normal[0], normal[2], t.cpu().numpy(), median_depth,
                                           pose_change(R, t, free_prior))
                if np.abs(shift).max() > 1e-9:  # the start moves: the pose scored here is not a candidate
                    dR = so3_exp(torch.from_numpy(shift[3:]).to(device))
                    R, t = dR @ R, dR @ t + torch.from_numpy(shift[:3]).to(device)
                    best_cost, best_Rt, at_best = float("inf"), None, None
                    continue
            delta = torch.from_numpy(constrained_step(normal[0], b.cpu().numpy(), normal[2], t.cpu().numpy(),
                                                     median_depth)).to(device)
            if not torch.isfinite(delta).all():
                break
            dR = so3_exp(delta[3:])
            R, t = dR @ R, dR @ t + delta[:3]
            if delta.norm() < 1e-6:
                break
        best, covariance = init_pose.clone(), None
        if best_Rt is not None:
            best = torch.eye(4)
            best[:3, :3], best[:3, 3] = best_Rt[0].float().cpu(), best_Rt[1].float().cpu()
            at_best = at_best or normal
            if at_best is not None:
                covariance = pose_covariance(*at_best, best[:3, 3].double().numpy(), median_depth)
        observed_fraction = float(seen.float().mean()) if seen is not None else float("nan")
        mapped = inside * (observed_fraction if seen is not None else 1.0)
        return TrackingResult(best, best_cost, len(pix), depth_fraction, inliers, observed_fraction, mapped,
                              covariance)
