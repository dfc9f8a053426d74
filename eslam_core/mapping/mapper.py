"""Mapping (paper Sec. 3.4): jointly optimise feature planes, decoders and the poses of a keyframe window.

Rays are drawn equally from every window frame. Window poses are optimised once `joint_poses_after` keyframes
exist, the oldest frame of the window held fixed (it anchors the gauge). The first frame is mapped alone with its
pose fixed, for more iterations at a higher learning rate.

Mapping runs on the field's device. Keyframes stay in host memory: each iteration draws its pixels there and sends
only the drawn rays' pixels, depths and colours (one batch, without waiting for the device); the refined poses and
the loss come back once, at the end of the step.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import torch

from eslam_core.config import Config, MappingConfig, RenderConfig
from eslam_core.cpu import denormals_flushed
from eslam_core.device import upload
from eslam_core.representation.field import SceneField
from eslam_core.frames import border_mask
from eslam_core.geometry import params_to_pose, pose_to_params
from eslam_core.mapping.keyframes import Keyframe
from eslam_core.mapping.plane_adam import RowSparseAdam
from eslam_core.rendering.losses import eslam_losses
from eslam_core.rendering.volume import render_rays


def import_optimiser_code() -> None:
    """Build and drop one Adam. A process's first torch optimiser imports torch's compiler stack (about 1 s on
    2 cores): a mapping process pays it before its first keyframe instead of inside the map's warm-up, which every
    tracked frame waits for."""
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])


@dataclass
class MappingResult:
    loss: float
    refined: dict  # keyframe position -> refined (4, 4) pose


class Mapper:
    def __init__(self, mapping: MappingConfig, render: RenderConfig, truncation: float, dirs_cam: torch.Tensor,
                 height: int, width: int):
        self.settings, self.render, self.truncation = mapping, render, truncation
        self.dirs_cam = dirs_cam  # on the field's device once mapping starts (see _on)
        self.width = width
        self.border = border_mask(height, width, mapping.border).reshape(-1)  # host: pixels are drawn there
        self.plane_adam = RowSparseAdam(betas=(0.9, 0.999))

    @staticmethod
    def of(cfg: Config, dirs_cam: torch.Tensor, height: int, width: int) -> "Mapper":
        """The mapper of `cfg`'s sections."""
        return Mapper(cfg.mapping, cfg.render, cfg.model.truncation, dirs_cam, height, width)

    def _on(self, device: torch.device) -> None:
        if self.dirs_cam.device != device:
            self.dirs_cam = self.dirs_cam.to(device)

    def _pixels(self, kf: Keyframe, n: int) -> torch.Tensor:
        """n pixels (indices into the keyframe's stored images) drawn uniformly (with replacement) from its usable
        ones. Usually most pixels are usable, so rejection sampling finds them without a pass over the image."""
        usable = kf.usable.reshape(-1)
        for _ in range(3):
            draw = torch.randint(len(usable), (2 * n,))
            draw = draw[self.border[kf.frame_pixels(draw, self.width)] & usable[draw]]
            if len(draw) >= n:
                return draw[:n]
        every = torch.arange(len(usable))
        candidates = torch.nonzero(self.border[kf.frame_pixels(every, self.width)] & usable).squeeze(1)
        if len(candidates) == 0:
            return candidates
        return candidates[torch.randint(len(candidates), (n,))]

    @denormals_flushed()  # see cpu.py
    def map(self, field: SceneField, keyframes, window: list[int], first: bool = False,
            optimise_poses: bool = False, after_iteration: Optional[Callable[[int], bool]] = None,
            iterations: Optional[int] = None) -> MappingResult:
        """`after_iteration(iterations done)`, called after every iteration, ends the step before its iteration count
        by returning True (the pipelined mapper does when it falls behind the tracker); it is also where the caller
        publishes the map mid-step or abandons the step by raising. `iterations`: the count, if not the config's."""
        mc = self.settings
        device = field.device
        self._on(device)
        if iterations is None:
            iterations = mc.first_iterations if first else mc.iterations
        lr_factor = mc.first_lr_factor if first else 1.0
        oldest = min(window, key=lambda i: keyframes[i].frame_index)
        free = [i for i in window if optimise_poses and i != oldest]
        poses = {i: keyframes[i].pose.to(device) for i in window}
        pose_params = {i: [p.requires_grad_(True) for p in pose_to_params(poses[i])] for i in free}
        groups = [{"params": field.decoder_parameters(), "lr": mc.lr_decoders * lr_factor}]
        if pose_params:
            groups.append({"params": [p for tq in pose_params.values() for p in tq], "lr": mc.lr_poses})
        planes = [field.geometry_planes, field.appearance_planes]
        # With the C kernel the planes get the row-sparse Adam (same result, cost of the window, not of the map);
        # otherwise a dense Adam whose fused kernel does the update in one pass (~8x faster on CPU than the loop).
        sparse = all(p.kernel() is not None for p in planes)
        if not sparse:
            groups.append({"params": field.plane_parameters(), "lr": mc.lr_planes * lr_factor})
        optim = torch.optim.Adam(groups, betas=(0.9, 0.999), fused=True)
        with self.plane_adam.fresh(planes if sparse else [], mc.lr_planes * lr_factor):
            last_loss = self._iterate(field, keyframes, window, poses, pose_params, iterations, optim,
                                      after_iteration)
        refined = {i: params_to_pose(*pose_params[i]).detach().cpu() for i in free}
        return MappingResult(float("nan") if last_loss is None else float(last_loss), refined)

    def _iterate(self, field: SceneField, keyframes, window: list[int], poses: dict, pose_params: dict,
                 iterations: int, optim: torch.optim.Optimizer, after_iteration) -> Optional[torch.Tensor]:
        """The step's iterations; returns the last loss (None if none ran)."""
        mc, device = self.settings, field.device
        per_frame = max(1, mc.rays // len(window))
        last_loss = None
        for it in range(iterations):
            drawn, frame_pix, d_gt, rgb_gt = [], [], [], []  # host: (window position, pixels) per frame
            for i in window:
                kf = keyframes[i]
                pix = self._pixels(kf, per_frame)
                if len(pix) == 0:
                    continue
                drawn.append((i, len(pix)))
                frame_pix.append(kf.frame_pixels(pix, self.width))
                d_gt.append(kf.depths(pix))
                rgb_gt.append(kf.colors(pix))
            if not drawn:
                break
            d_gt_host = torch.cat(d_gt)
            # The rays without depth are known here: the renderer need not ask the device for them.
            missing = upload(torch.nonzero(d_gt_host <= 0).squeeze(1), device)
            counts = [n for _, n in drawn]
            rays_dirs = self.dirs_cam[upload(torch.cat(frame_pix), device)].split(counts)
            origins, dirs = [], []
            for (i, n), dirs_cam in zip(drawn, rays_dirs):
                c2w = params_to_pose(*pose_params[i]) if i in pose_params else poses[i]
                dirs.append(dirs_cam @ c2w[:3, :3].T)
                origins.append(c2w[:3, 3].expand(n, 3))
            d_gt_all = upload(d_gt_host, device)
            out = render_rays(field, torch.cat(origins), torch.cat(dirs), d_gt_all, self.render,
                              self.truncation, missing)
            loss = eslam_losses(out, d_gt_all, upload(torch.cat(rgb_gt), device), self.truncation
                                ).total(mc.weights)
            optim.zero_grad(set_to_none=True)
            loss.backward()
            optim.step()
            self.plane_adam.step()
            last_loss = loss.detach()
            if after_iteration is not None and after_iteration(it + 1):
                break
        return last_loss
