"""The keyframe store: compact storage under a memory budget, and the overlap-based choice of the mapping window
(paper Sec. 3.4).

Keyframes are kept as uint8 colour and 16-bit depth (0.2 mm steps, up to 13.1 m): 1.76 MB for a 640x480 frame,
instead of ~22 MB as float64 in the official implementation. A camera that runs for hours still makes a keyframe
every few frames. A camera that comes back (or stands still) makes keyframes that others already cover: a new
keyframe whose surface an older one sees nearly all of from about the same pose is *redundant*; it serves the
mapping windows while it is among the newest `KEEP_FULL` and is dropped when it leaves them, so that the store grows
with the explored space, not with time. The older keyframe is the one kept: replacing it instead (as this store
first did) let the map drift with every revisit, each new keyframe posed against a map that the previous
replacements had fitted (on ICL played back and forth, the lap ATE went from 0.65 to 2.9 cm in 9 minutes of input).
The store also has a budget (`mapping.keyframe_budget_mb`). Over it, the oldest keyframes (not the newest
`KEEP_FULL`) are *reduced*: their images are kept at every `REDUCED_STRIDE`-th pixel along both axes (1/16 of the
bytes; mapping draws its few hundred rays per keyframe from the ~19k pixels left). When every old keyframe is
reduced and the store is still over budget, the reduced keyframe that overlaps the newest keyframe's view most (the
overlap the window selection measures) is dropped: the newest keyframe sees the same surface, and the feature planes
keep what was learnt from the dropped one.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from eslam_core.camera import Intrinsics
from eslam_core.frames import rgb_uint8

DEPTH_STEP = 1.0 / 5000.0  # metres per unit of the stored depth
DEPTH_MAX = 65535 * DEPTH_STEP
REDUCED_STRIDE = 4
KEEP_FULL = 8  # the newest keyframes, which every mapping window holds, are never reduced
# A new keyframe is redundant when an older one sees this much of its surface from about the same place (closer
# than the distance, turned less than the angle).
REDUNDANT_OVERLAP, REDUNDANT_DISTANCE_M, REDUNDANT_ANGLE_DEG = 0.9, 0.15, 15.0


@dataclass
class Keyframe:
    frame_index: int
    timestamp: float
    rgb: torch.Tensor  # (H, W, 3) uint8
    depth: torch.Tensor  # (H, W) int32-decoded uint16 storage, see DEPTH_STEP
    usable: torch.Tensor  # (H, W) bool: pixel may be sampled (e.g. not observing geometry outside the bound)
    pose: torch.Tensor  # (4, 4) float32 camera-to-world, refined by mapping
    number: int = 0  # 0, 1, ... in order of creation: the keyframe's name in the trajectory and in messages
    stride: int = 1  # the images hold every stride-th pixel of the frame along both axes (reduced keyframe)
    redundant: bool = False  # an older keyframe covers its view: dropped once it is not among the newest

    @staticmethod
    def from_tensors(frame_index: int, timestamp: float, rgb: torch.Tensor, depth: torch.Tensor,
                     usable: torch.Tensor, pose: torch.Tensor, number: int = 0) -> "Keyframe":
        """A keyframe in host memory (whatever device the tensors come from: the store grows with time, the
        device's memory is for the map; mapping sends the rays it draws)."""
        rgb8 = rgb_uint8(rgb)
        d = torch.where(depth < DEPTH_MAX, depth, torch.zeros_like(depth))
        d16 = (d / DEPTH_STEP + 0.5).to(torch.int32).to(torch.int16).cpu()  # stores uint16 bits in int16
        return Keyframe(frame_index, timestamp, rgb8, d16, usable.cpu().clone(), pose.detach().cpu().clone(), number)

    def moved(self, T: np.ndarray) -> "Keyframe":
        """The keyframe with its pose seen from another frame (`T` @ pose, T 4x4: a submap's anchor or its
        inverse); the images shared."""
        return replace(self, pose=torch.from_numpy(np.asarray(T, dtype=np.float64) @ self.pose.double().numpy())
                       .float())

    def reduced(self) -> "Keyframe":
        s, o = REDUCED_STRIDE, REDUCED_STRIDE // 2
        return replace(self, rgb=self.rgb[o::s, o::s].clone(), depth=self.depth[o::s, o::s].clone(),
                       usable=self.usable[o::s, o::s].clone(), stride=s)

    def frame_pixels(self, flat_idx: torch.Tensor, width: int) -> torch.Tensor:
        """Flat pixel indices in the full frame (of `width` columns) of flat indices into the stored images."""
        if self.stride == 1:
            return flat_idx
        w = self.usable.shape[1]
        o = self.stride // 2
        return (flat_idx // w * self.stride + o) * width + flat_idx % w * self.stride + o

    def frame_depth_image(self, height: int, width: int) -> torch.Tensor:
        """The depth image at the frame's resolution (a reduced keyframe's by nearest neighbour)."""
        d = self.depth_image()
        if self.stride == 1:
            return d
        full = d.repeat_interleave(self.stride, 0).repeat_interleave(self.stride, 1)
        return torch.nn.functional.pad(full, (0, max(0, width - full.shape[1]), 0, max(0, height - full.shape[0])))[
            :height, :width]

    def colors(self, flat_idx: torch.Tensor) -> torch.Tensor:
        return self.rgb.reshape(-1, 3)[flat_idx].float() / 255.0

    def depths(self, flat_idx: torch.Tensor) -> torch.Tensor:
        raw = self.depth.reshape(-1)[flat_idx].to(torch.int32) & 0xFFFF
        return raw.float() * DEPTH_STEP

    def depth_image(self) -> torch.Tensor:
        return (self.depth.to(torch.int32) & 0xFFFF).float() * DEPTH_STEP

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.rgb, self.depth, self.usable, self.pose))


def overlap_fractions(points_world: torch.Tensor, poses: torch.Tensor, intr: Intrinsics,
                      margin: int = 20) -> torch.Tensor:
    """Fraction of the points that each keyframe (K, 4, 4) sees in front of it and inside its image."""
    w2c = torch.linalg.inv(poses)
    p = torch.einsum("kij,nj->kni", w2c[:, :3, :3], points_world) + w2c[:, None, :3, 3]
    z = p[..., 2]
    u, v = intr.project(p)
    inside = (z > 0) & (u >= margin) & (u < intr.width - margin) & (v >= margin) & (v < intr.height - margin)
    return inside.float().mean(-1)


class KeyframeStore:
    """The keyframes mapping can use, oldest first, under a memory budget (see the module docstring)."""

    def __init__(self, budget_bytes: int, keep_full: int = KEEP_FULL):
        self.budget_bytes = budget_bytes
        self.keep_full = keep_full
        self.items: list[Keyframe] = []
        self.made = 0  # keyframes ever added (the next keyframe's number)
        self.reduced = 0
        self.dropped = 0
        self.dropped_numbers: list[int] = []  # dropped since the owner last took them (take_dropped)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, position: int) -> Keyframe:
        return self.items[position]

    def __iter__(self):
        return iter(self.items)

    def nbytes(self) -> int:
        return sum(kf.nbytes() for kf in self.items)

    def append(self, kf: Keyframe, intr: Intrinsics, newest_points: torch.Tensor | None = None) -> None:
        """Add the newest keyframe, then reduce or drop older ones until the store fits its budget.
        `newest_points`: world points of its surface, to find the keyframe it makes redundant."""
        self.items.append(kf)
        self.made = max(self.made, kf.number + 1)
        if newest_points is not None and len(newest_points):
            kf.redundant = self._covered(kf, newest_points, intr)
        for i in range(len(self.items) - self.keep_full - 1, -1, -1):  # redundant ones that left the newest
            if self.items[i].redundant:
                self.dropped_numbers.append(self.items.pop(i).number)
                self.dropped += 1
        if self.budget_bytes <= 0:
            return
        total = self.nbytes()
        for i in range(max(0, len(self.items) - self.keep_full)):
            if total <= self.budget_bytes:
                return
            if self.items[i].stride == 1:
                before = self.items[i].nbytes()
                self.items[i] = self.items[i].reduced()
                total += self.items[i].nbytes() - before
                self.reduced += 1
        while total > self.budget_bytes and len(self.items) > self.keep_full:
            old = range(len(self.items) - self.keep_full)
            if newest_points is not None and len(newest_points):
                overlap = overlap_fractions(newest_points, torch.stack([self.items[i].pose for i in old]), intr)
                victim = int(overlap.argmax())
            else:
                victim = 0
            gone = self.items.pop(victim)
            total -= gone.nbytes()
            self.dropped += 1
            self.dropped_numbers.append(gone.number)

    def _covered(self, kf: Keyframe, points: torch.Tensor, intr: Intrinsics) -> bool:
        """Whether an older keyframe that stays (not redundant itself) sees nearly all of `kf`'s surface from about
        its pose."""
        older = [other for other in self.items[:-1] if not other.redundant]
        if not older:
            return False
        poses = torch.stack([other.pose for other in older])
        near = (poses[:, :3, 3] - kf.pose[:3, 3]).norm(dim=1) < REDUNDANT_DISTANCE_M
        cos = ((poses[:, :3, 2] * kf.pose[:3, 2]).sum(1)).clamp(-1, 1)
        near &= cos > np.cos(np.radians(REDUNDANT_ANGLE_DEG))
        if not near.any():
            return False
        overlap = overlap_fractions(points, poses[torch.nonzero(near).squeeze(1)], intr, margin=0)
        return float(overlap.max()) >= REDUNDANT_OVERLAP

    def take_dropped(self) -> list[int]:
        """Numbers of the keyframes dropped since the last call (for what indexes keyframes elsewhere)."""
        out, self.dropped_numbers = self.dropped_numbers, []
        return out

    def replace_all(self, keyframes: list[Keyframe]) -> None:
        self.items = list(keyframes)
        self.made = max([self.made] + [kf.number + 1 for kf in keyframes])

    def position(self, number: int) -> int | None:
        for i in range(len(self.items) - 1, -1, -1):
            if self.items[i].number == number:
                return i
        return None


def select_window(keyframes, current: int, points_world: torch.Tensor, intr: Intrinsics,
                  window: int, generator: np.random.Generator) -> list[int]:
    """Keyframe positions for a mapping step: W-3 random overlapping ones + the previous two + the current one."""
    previous = [i for i in (current - 2, current - 1) if i >= 0]
    others = [i for i in range(current) if i not in previous]
    chosen: list[int] = []
    if others and window > 3:
        frac = overlap_fractions(points_world, torch.stack([keyframes[i].pose for i in others]), intr)
        overlapping = [i for i, f in zip(others, frac.tolist()) if f > 0]
        generator.shuffle(overlapping)
        chosen = overlapping[: window - 3]
    return sorted(chosen + previous + [current])
