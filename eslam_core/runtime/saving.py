"""Saving a runtime's state: the same for every runtime, given `snapshot()` (a SLAM) and `trajectory()`.

Each save is written whole or not at all (eslam_core.atomic): a failure, a full disk included, is one
OutputWriteError line and leaves an older file of the same name as it was."""
from __future__ import annotations

from pathlib import Path

from eslam_core.trajectory import Trajectory
from eslam_core.outputs.export import map_mesh, save_checkpoint, save_trajectory
from eslam_core.outputs.mesh import save_ply


class SavingMixin:
    def save_checkpoint(self, path) -> Path:
        return save_checkpoint(self.snapshot(), Path(path))

    def save_mesh(self, path, resolution: float | None = None) -> Path:
        return save_ply(map_mesh(self.snapshot(), resolution or self.cfg.mesh.resolution), Path(path))

    def save_trajectory(self, path) -> Path:
        timestamps, poses = self.trajectory()
        return save_trajectory(Trajectory(timestamps, poses), Path(path))
