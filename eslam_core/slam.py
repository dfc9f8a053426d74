"""The SLAM system in lock-step: track every frame against the current map, and every `mapping.every` frames make
the frame a keyframe and run a mapping step (paper Sec. 3.4).

The parts are the tracking front end (`tracking/frontend.py`), the scene map (`mapping/scene_map.py`) and the
trajectory (`trajectory.py`); the pipelined runtime assembles the same parts in its two processes.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import torch

from eslam_core.camera import Frame, Intrinsics
from eslam_core.config import Config, config_from_dict
from eslam_core.cpu import keep_freed_memory
from eslam_core.frames import PreparedFrame, pixel_directions_table, prepare_frame, working_intrinsics
from eslam_core.mapping.keyframes import Keyframe
from eslam_core.mapping.scene_map import SceneMap, initial_extent
from eslam_core.tracking.frontend import TrackingFrontEnd
from eslam_core.trajectory import TrackedTrajectory

CHECKPOINT_VERSION = 4


@dataclass
class StepResult:
    index: int
    pose: np.ndarray
    tracking_loss: float
    keyframe: bool
    mapping_loss: float
    refined: dict  # keyframe number -> refined pose, from this step's mapping
    quality: float  # of the tracked pose (tracking/quality.py)
    lost: bool  # the camera is lost: the pose is a guess, the frame was not mapped
    anchor: bool  # the frame's record anchors the trajectory: a keyframe, or (localization) every frame
    covariance: Optional[np.ndarray] = None  # (6, 6) of the tracked pose, x y z roll pitch yaw (information.py)
    degraded: bool = False  # the view leaves the pose free in some direction: not mapped (quality.py)


def new_keyframe(pf: PreparedFrame, pose: torch.Tensor, number: int) -> Keyframe:
    return Keyframe.from_tensors(pf.index, pf.timestamp, pf.rgb, pf.depth, torch.ones_like(pf.depth, dtype=torch.bool),
                                 pose, number)


class SLAM:
    def __init__(self, cfg: Config, intrinsics: Intrinsics):
        keep_freed_memory()  # process-wide, see cpu.py
        self.cfg = cfg
        self.input_intrinsics = intrinsics
        self.intr = working_intrinsics(intrinsics, cfg.camera)
        self.dirs_cam = pixel_directions_table(self.intr)
        self.frontend = TrackingFrontEnd(cfg, self.intr, self.dirs_cam)
        self.map = SceneMap(cfg, self.intr, self.dirs_cam)
        self.trajectory = TrackedTrajectory()
        self.stop_mapping_early: Optional[Callable[[int], bool]] = None  # see Mapper.map (set by the runtime)

    def step(self, frame: Frame) -> StepResult:
        pf = prepare_frame(frame, self.input_intrinsics, self.cfg.camera)
        if not self.map.started:
            pose0 = self.frontend.first_pose(pf, self.trajectory)
            self.map.start(initial_extent(self.cfg, pf, self.intr, pose0))
            self.trajectory.record(pf.index, pf.timestamp, pose0, 0.0, pf.gt_pose, keyframe=True)
            kf = new_keyframe(pf, torch.from_numpy(pose0).float(), 0)
            self.frontend.remember(kf)
            self.map.add_keyframe(kf)
            step = self.map.warm_up()
            return StepResult(pf.index, pose0, 0.0, True, step.loss, {}, 1.0, False, True)
        tracked = self.frontend.track(pf, self.map, self.trajectory)
        pose = tracked.pose.double().numpy()
        n = len(self.trajectory)
        # Localization refines nothing: each frame is its own anchor (its pose as tracked).
        anchor = tracked.keyframe or self.cfg.run.mode == "localization"
        self.trajectory.record(pf.index, pf.timestamp, pose, tracked.loss, pf.gt_pose, anchor,
                               tracked.quality.value, tracked.lost, tracked.quality.degraded, tracked.covariance_matrix)
        mapping_loss, refined = float("nan"), {}
        if tracked.keyframe:
            number = self.trajectory.keyframes - 1
            kf = new_keyframe(pf, tracked.pose, number)
            self.frontend.remember(kf)
            self.map.add_keyframe(kf)
            self.frontend.forget(self.map.keyframes.take_dropped())
            step = self.map.map_newest(self.stop_mapping_early)
            self.trajectory.refine(step.refined)
            self.frontend.refine(step.refined)
            mapping_loss, refined = step.loss, step.refined
        return StepResult(pf.index, self.trajectory.pose(n), tracked.loss, tracked.keyframe, mapping_loss, refined,
                          tracked.quality.value, tracked.lost, anchor, tracked.covariance_matrix,
                          tracked.quality.degraded)

    # ------------------------------------------------------------------------------------------------ checkpoint
    def state_dict(self) -> dict:
        return {
            "version": CHECKPOINT_VERSION,
            "config": self.cfg.to_dict(),
            "intrinsics": self.input_intrinsics.__dict__,
            "map": self.map.state_dict(),
            "trajectory": self.trajectory.state_dict(),
        }

    @staticmethod
    def from_state_dict(state: dict, device: str = "auto") -> "SLAM":
        if not isinstance(state, dict) or "map" not in state and "field" not in state:
            raise ValueError("not an ESLAM checkpoint (no map inside)")
        if state.get("version") != CHECKPOINT_VERSION:
            raise ValueError(f"checkpoint version {state.get('version')} is not supported (expected "
                                  f"{CHECKPOINT_VERSION}); re-run `eslam run` to produce a new checkpoint")
        # A checkpoint runs where it is loaded (`device`), not necessarily where it was made (that GPU may be absent).
        cfg = dict(state["config"], run=dict(state["config"].get("run", {}), device=device))
        slam = SLAM(config_from_dict(cfg, "checkpoint"), Intrinsics(**state["intrinsics"]))
        slam.map.load_state_dict(state["map"])
        slam.trajectory = TrackedTrajectory.from_state_dict(state["trajectory"])
        slam.frontend.start_lost(slam.map.keyframes)
        return slam


def loaded_slam(path, cfg: Config, intrinsics: Intrinsics) -> "SLAM":
    """A saved map to go on with (`run.mode` slam) or to localize against (localization: the trajectory starts
    empty), for frames of `intrinsics`; it starts lost. The map must pass `read_loadable`'s checks."""
    state = read_loadable(path, cfg, intrinsics)
    state["config"].setdefault("run", {})["mode"] = cfg.run.mode
    slam = SLAM.from_state_dict(state)
    if cfg.run.mode == "localization":
        slam.trajectory = TrackedTrajectory()
    return slam


def loaded_trajectory(path, cfg: Config, intrinsics: Intrinsics) -> TrackedTrajectory:
    """The trajectory `loaded_slam` starts with, without building the map (the pipelined runtime's parent needs
    only this; its workers load the map)."""
    state = read_loadable(path, cfg, intrinsics)
    if cfg.run.mode == "localization":
        return TrackedTrajectory()
    return TrackedTrajectory.from_state_dict(state["trajectory"])


def read_loadable(path, cfg: Config, intrinsics: Optional[Intrinsics]) -> dict:
    """The state of the checkpoint at `path` if a runtime of `cfg` can load it for frames of `intrinsics` (None:
    the camera is not checked): intact, of this version and compatible (map_file.check_compatible); a
    CheckpointError line otherwise. Every map load goes through here, and so does ~/load_map before it drops
    the node's map."""
    from eslam_core.outputs.map_file import check_compatible, read_checkpoint  # (outputs/ builds on this module)

    state = read_checkpoint(path, CHECKPOINT_VERSION)
    check_compatible(state, cfg, intrinsics, path)
    return state
