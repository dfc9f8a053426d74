"""Saving a runtime's state: the same for every runtime, given `snapshot()` (a SLAM) and `trajectory()`."""
from __future__ import annotations

from pathlib import Path

from eslam_core.evaluation.trajectory import Trajectory, write_tum
from eslam_core.outputs.export import map_mesh, save_checkpoint
from eslam_core.outputs.mesh import save_ply


class SavingMixin:
    def save_checkpoint(self, path) -> Path:
        return save_checkpoint(self.snapshot(), Path(path))

    def save_mesh(self, path, resolution: float | None = None) -> Path:
        return save_ply(map_mesh(self.snapshot(), resolution or self.cfg.mesh.resolution), Path(path))

    def save_trajectory(self, path) -> Path:
        timestamps, poses = self.trajectory()
        return write_tum(Path(path), Trajectory(timestamps, poses))
