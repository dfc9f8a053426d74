"""The SLAM system in lock-step: track every frame against the current map, and every `mapping.every` frames make
the frame a keyframe and run a mapping step (paper Sec. 3.4).

The parts are the tracking session (`tracking/session.py`: front end, trajectory, keyframe making) and the scene map
(`mapping/scene_map.py`); the pipelined runtime's two processes drive the same parts.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from eslam_core.camera import Frame, Intrinsics
from eslam_core.config import Config, config_from_dict
from eslam_core.cpu import keep_freed_memory
from eslam_core.frames import pixel_directions_table, prepare_frame, working_intrinsics
from eslam_core.map_file import check_compatible, read_checkpoint
from eslam_core.mapping.scene_map import MappingStep, SceneMap
from eslam_core.submaps.atlas import Atlas
from eslam_core.tracking.session import PoseCorrections, TrackingSession
from eslam_core.trajectory import TrackedTrajectory

log = logging.getLogger("eslam")

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


class SLAM:
    def __init__(self, cfg: Config, intrinsics: Intrinsics):
        keep_freed_memory()  # process-wide, see cpu.py
        self.cfg = cfg
        self.input_intrinsics = intrinsics
        self.intr = working_intrinsics(intrinsics, cfg.camera)
        self.dirs_cam = pixel_directions_table(self.intr)
        self.tracking = TrackingSession(cfg, self.intr, self.dirs_cam)
        self.atlas = Atlas(cfg, self.intr, self.dirs_cam)  # the submaps (one, with submaps.radius_m 0)
        self.atlas.new_submap(None)
        # Called after every mapping iteration (Mapper.map): the runtime's way to end a step early or abandon it.
        self.after_mapping_iteration: Optional[Callable[[int], bool]] = None

    @property
    def trajectory(self) -> TrackedTrajectory:
        return self.tracking.trajectory

    @property
    def map(self) -> SceneMap:
        """The active submap (the map, with one)."""
        return self.atlas.active

    def step(self, frame: Frame) -> StepResult:
        pf = prepare_frame(frame, self.input_intrinsics, self.cfg.camera)
        n = len(self.trajectory)
        if not self.map.started:
            tracked, kf = self.tracking.first(pf)
            self.tracking.remember(kf)
            self.map.start(tracked.extent)
            self.map.add_keyframe(self.atlas.local(self.map, kf))
            step = self.map.warm_up(self.after_mapping_iteration)
            return StepResult(pf.index, self.trajectory.pose(n), 0.0, True, step.loss, {}, 1.0, False, True)
        tracked = self.tracking.step(pf, self.map)
        mapping_loss, refined, dropped = float("nan"), {}, ()
        if tracked.keyframe_due:
            kf = self.tracking.new_keyframe(pf, tracked)
            self.tracking.remember(kf)
            step, sub = self._map_keyframe(kf)
            refined = self.atlas.to_world(sub, step.refined)
            dropped = tuple(n for n in sub.keyframes.take_dropped() if self.atlas.owns(sub, n))
            mapping_loss = step.loss
        # Keyframes placed by other submaps' (loops), as soon as a check ends: also on a frame that made no keyframe
        # (a relocalization checks every waiting keyframe first; a lost camera makes none).
        for check in self.tracking.take_checks():
            refined.update(self.atlas.close_loop(check, pf.index, pf.timestamp))
        if refined or dropped:
            self.tracking.apply(PoseCorrections(refined, dropped))
        pose = tracked.pose
        if self.cfg.run.mode == "localization" and (not pose.lost or pose.relocalized_from is not None):
            self.atlas.follow(pose.pose.double().numpy()[:3, 3], pose.relocalized_from)  # (no keyframe places it)
        return StepResult(pf.index, self.trajectory.pose(n), pose.loss, pose.keyframe, mapping_loss, refined,
                          pose.quality.value, pose.lost, tracked.anchor, pose.covariance_matrix,
                          pose.quality.degraded)

    def _map_keyframe(self, kf) -> tuple[MappingStep, SceneMap]:
        """A new keyframe into its submap (Atlas.place) and a mapping step there; a submap that begins with it is
        warmed up as the first map was."""
        sub, began = self.atlas.place(kf)
        return (sub.warm_up if began else sub.map_newest)(self.after_mapping_iteration), sub

    # ------------------------------------------------------------------------------------------------ checkpoint
    def state_dict(self) -> dict:
        return {
            "version": CHECKPOINT_VERSION,
            "config": self.cfg.to_dict(),
            "intrinsics": self.input_intrinsics.__dict__,
            "map": self.map.state_dict(),
            "trajectory": self.trajectory.state_dict(),
            # With several submaps: all of them and the pose graph (the "map" above is the active one's).
            **({"atlas": self.atlas.state_dict()} if len(self.atlas.submaps) > 1 else {}),
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
        slam = SLAM(config_from_dict(cfg, "checkpoint", migrate=True), Intrinsics(**state["intrinsics"]))
        if "atlas" in state:
            slam.atlas = Atlas(slam.cfg, slam.intr, slam.dirs_cam)
            slam.atlas.load_state_dict(state["atlas"])
        else:
            slam.atlas.load_single_map(state["map"])
        slam.tracking.trajectory = TrackedTrajectory.from_state_dict(state["trajectory"])
        slam.tracking.frontend.start_lost(slam.atlas.world_keyframes())
        return slam


def loaded_slam(path, cfg: Config, intrinsics: Intrinsics) -> "SLAM":
    """A saved map to go on with (`run.mode` slam) or to localize against (localization: the trajectory starts
    empty), for frames of `intrinsics`; it starts lost. The map must pass `read_loadable`'s checks."""
    state = read_loadable(path, cfg, intrinsics)
    state["config"].setdefault("run", {})["mode"] = cfg.run.mode
    slam = SLAM.from_state_dict(state)
    if cfg.run.mode == "localization":
        slam.tracking.trajectory = TrackedTrajectory()
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
    state = read_checkpoint(path, CHECKPOINT_VERSION)
    check_compatible(state, cfg, intrinsics, path)
    return state
