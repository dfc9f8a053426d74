"""Observed space: the voxels of the scene bound that lie near a surface some keyframe saw.

Mapping fits the SDF only along keyframe rays; elsewhere the decoded SDF is whatever the initial plane features
give, often a small value that looks like a surface. The fast SDF tracker aligns depth points to the SDF, so points
on geometry the map has not seen yet (a wall coming into view) would pull the pose towards that fake surface. The
tracker therefore uses only points inside observed space. The grid is coarse (one truncation per voxel, grown by
one voxel), so keyframe pose refinements of a few centimetres do not matter.

The grid lives on the map's device (the trackers ask it about their points every frame); points to add may come
from the host (keyframes are kept there).
"""
from __future__ import annotations

from collections import deque

import numpy as np
import torch


def voxels_to_cover(length: np.ndarray, voxel: float) -> np.ndarray:
    """Whole voxels covering `length` along each axis. A map's bounds fall on voxel edges (whole coarse cells), and a
    grid's float32 origin is off by up to ~4e-6 voxels there: that rounding must not add a voxel (the grid would
    drift from the bounds as the map grows) nor drop one (a grown grid was once a voxel short of the old one, and
    the mapper crashed)."""
    return np.ceil(np.asarray(length) / voxel - 1e-3).astype(int)


class ObservedSpace:
    def __init__(self, bound: np.ndarray, voxel: float, device: torch.device | str | None = None):
        self.origin = torch.tensor(bound[0], dtype=torch.float32, device=device)
        self.voxel = voxel
        self.shape = tuple(int(n) for n in voxels_to_cover(bound[1] - bound[0], voxel))
        self._shape = torch.tensor(self.shape, device=device)
        self.seen = torch.zeros(self.shape, dtype=torch.bool, device=device)
        self._near: torch.Tensor | None = None  # `seen` grown by one voxel, computed when first needed

    @property
    def device(self) -> torch.device:
        return self.seen.device

    def grown(self, bound: np.ndarray) -> "ObservedSpace":
        """The same observed voxels in a grid over a larger bound (aligned to this grid's voxels)."""
        origin = self.origin.double().cpu().numpy()
        shift = voxels_to_cover(origin - bound[0], self.voxel).clip(min=0)
        new = ObservedSpace(np.stack([origin - shift * self.voxel, bound[1]]), self.voxel, self.device)
        i, j, k = shift
        new.seen[i: i + self.shape[0], j: j + self.shape[1], k: k + self.shape[2]] = self.seen
        return new

    def _voxels(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        ijk = torch.floor((points - self.origin) / self.voxel).long()
        inside = ((ijk >= 0) & (ijk < self._shape)).all(-1)
        return ijk, inside

    def add(self, points: torch.Tensor) -> None:
        """Mark the voxels holding these surface points (world frame, (N, 3), any device)."""
        ijk, inside = self._voxels(points.to(self.device))
        ijk = ijk[inside]
        self.seen[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
        self._near = None

    def contains(self, points: torch.Tensor) -> torch.Tensor:
        """(N,) bool on the grid's device: the point lies within about a voxel of observed surface."""
        if self._near is None:
            self._near = grow_by_one_voxel(self.seen)
        ijk, inside = self._voxels(points.to(self.device))
        # Every point reads a voxel (outside ones a clamped one, then masked): no selection whose size the host
        # would have to wait for.
        ijk = torch.minimum(ijk.clamp_min(0), self._shape - 1)
        return self._near[ijk[:, 0], ijk[:, 1], ijk[:, 2]] & inside


def grow_by_one_voxel(grid: torch.Tensor) -> torch.Tensor:
    """A boolean 3D grid dilated by its 26-neighbourhood: a 3x3x3 box is separable, so three 1D passes (about 25x
    cheaper than max_pool3d on floats)."""
    grown = grid
    for axis in range(3):
        n = grown.shape[axis]
        out = grown.clone()
        out.narrow(axis, 1, n - 1).logical_or_(grown.narrow(axis, 0, n - 1))
        out.narrow(axis, 0, n - 1).logical_or_(grown.narrow(axis, 1, n - 1))
        grown = out
    return grown


class ObservedSurfaces:
    """Observed space fed with the keyframes' surface points as mapping fits them. The newest keyframe's single
    mapping step shares the rays with the whole window and leaves space seen for the first time rough: a keyframe
    joins observed space (`space`) after the step that follows its own, the first one after its warm-up. The steps
    of the next keyframes, whose windows hold it, go on fitting it: a keyframe joins settled space (`settled`) once
    `after` newer keyframes are mapped. The SDF tracker aligns to settled space where it can (see `alignable`)."""

    def __init__(self, bound: np.ndarray, voxel: float, device: torch.device | str | None = None, after: int = 1):
        self.space = ObservedSpace(bound, voxel, device)
        self.settled = ObservedSpace(bound, voxel, device)
        self.pending: deque = deque()  # surface points of keyframes not settled yet, oldest first
        self.joined = 0  # keyframes in observed space
        self.settled_count = 0  # keyframes in settled space (the first ones of those joined)
        self.after = after

    def add_keyframe(self, points: torch.Tensor) -> None:
        self.pending.append(points)

    def mapped(self, keyframes: int) -> None:
        """The map is now fitted to the first `keyframes` keyframes."""
        observed, settled = (min(keyframes, max(1, keyframes - lag)) for lag in (1, self.after))
        while self.joined < observed and self.joined - self.settled_count < len(self.pending):
            self.space.add(self.pending[self.joined - self.settled_count])
            self.joined += 1
        while self.settled_count < min(settled, self.joined):
            self.settled.add(self.pending.popleft())
            self.settled_count += 1

    def settle_all(self) -> None:
        """Every keyframe joins both: a loaded map's fitting is over."""
        self.mapped(self.settled_count + len(self.pending) + self.after)

    def grow(self, bound: np.ndarray) -> None:
        self.space = self.space.grown(bound)
        self.settled = self.settled.grown(bound)

    def alignable(self, points: torch.Tensor, settled_share: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
        """The points to align the frame with and those in observed space. Those in settled space, unless they are
        fewer than `settled_share` of those in observed space: a camera turning towards new space outruns settled
        space (it lags `after` keyframes), and aligning a few points there lost the long room's camera (test_growth),
        so then those in observed space."""
        seen, settled = self.space.contains(points), self.settled.contains(points)  # settled within seen
        return (settled if settled.sum() >= settled_share * seen.sum() else seen), seen

    def contains(self, points: torch.Tensor) -> torch.Tensor:
        return self.space.contains(points)
