"""The tracking front end: the pose of each new frame, and whether it becomes a keyframe.

Prediction: the motion of an external odometry between the last frame and this one when frames carry
`odom_pose`, else constant velocity (scaled by the time gaps), else the last pose. Tracking refines the prediction
against the map (the paper's rendering tracker or the fast SDF alignment); with `tracking.mode: external` the
odometry's pose (expressed in the map frame by the first frame) is taken as it is. A pose is re-orthonormalised
where it is made, and a diverged optimisation keeps the prediction. Every `mapping.every`-th frame is a keyframe.

What the front end needs of the map (`MapView`) is the field, its extent, observed space and the newest keyframe:
the lock-step system gives it the `SceneMap` itself, the tracking process its replica of the mapper's map.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional, Protocol

import numpy as np
import torch

from eslam_core.camera import Intrinsics
from eslam_core.config import Config
from eslam_core.frames import PreparedFrame
from eslam_core.geometry import depth_points_world, orthonormalize
from eslam_core.mapping.extent import outside_mask
from eslam_core.mapping.keyframes import Keyframe
from eslam_core.mapping.observed import ObservedSurfaces
from eslam_core.representation.field import SceneField
from eslam_core.tracking.render_tracker import constant_velocity, make_tracker, time_ratio
from eslam_core.trajectory import TrackedTrajectory

log = logging.getLogger("eslam")


class MapView(Protocol):
    field: Optional[SceneField]
    extent: Optional[np.ndarray]
    observed: Optional[ObservedSurfaces]

    def newest_keyframe(self) -> Optional[Keyframe]: ...


@dataclass
class TrackedPose:
    pose: torch.Tensor  # (4, 4) float32 camera-to-world
    prediction: torch.Tensor
    loss: float
    keyframe: bool


class TrackingFrontEnd:
    def __init__(self, cfg: Config, intr: Intrinsics, dirs_cam: torch.Tensor):
        self.cfg, self.intr, self.dirs_cam = cfg, intr, dirs_cam
        self.tracker = make_tracker(cfg, dirs_cam, intr) if cfg.tracking.mode == "track" else None
        self.map_from_odom: Optional[np.ndarray] = None  # fixed by the first frame that carries odometry
        self.last_odom: Optional[np.ndarray] = None

    def first_pose(self, pf: PreparedFrame) -> np.ndarray:
        """The first frame fixes the map frame: its ground-truth pose when known (outputs share its frame)."""
        pose0 = pf.gt_pose if pf.gt_pose is not None else np.eye(4)
        self._note_odometry(pf, pose0)
        return orthonormalize(pose0)

    def _note_odometry(self, pf: PreparedFrame, pose: np.ndarray) -> None:
        if pf.odom_pose is None:
            return
        if self.map_from_odom is None:
            self.map_from_odom = pose @ np.linalg.inv(pf.odom_pose)
        self.last_odom = pf.odom_pose

    def predict(self, pf: PreparedFrame, trajectory: TrackedTrajectory) -> np.ndarray:
        n = len(trajectory)
        prev = trajectory.pose(n - 1)
        if pf.odom_pose is not None and self.last_odom is not None:
            if self.cfg.tracking.mode == "external":
                return self.map_from_odom @ pf.odom_pose
            return prev @ np.linalg.inv(self.last_odom) @ pf.odom_pose
        if n < 2 or not self.cfg.tracking.constant_velocity:
            return prev
        ratio = time_ratio(trajectory.records[n - 2].timestamp, trajectory.records[n - 1].timestamp, pf.timestamp)
        return constant_velocity(trajectory.pose(n - 2), prev, ratio)

    def track(self, pf: PreparedFrame, view: MapView, trajectory: TrackedTrajectory) -> TrackedPose:
        init = torch.from_numpy(orthonormalize(self.predict(pf, trajectory))).float()
        keyframe = len(trajectory) % self.cfg.mapping.every == 0
        if self.tracker is None:  # external mode: the odometry's pose, mapping only
            self._note_odometry(pf, init.double().numpy())
            return TrackedPose(init, init, 0.0, keyframe)
        # The extent test uses the predicted pose: a few centimetres off at most, and it saves a second pass.
        usable = self.inside_map(pf, view.extent, init)
        result = self.tracker.track(view.field, pf, init, usable, view.observed.space, view.newest_keyframe())
        pose = result.pose
        if not torch.isfinite(pose).all():  # a diverged optimisation must not poison the trajectory and the map
            log.warning("frame %d: tracking diverged (non-finite pose); keeping the motion model's prediction",
                        pf.index)
            pose = init
        pose = orthonormalize(pose)
        self._note_odometry(pf, pose.double().numpy())
        return TrackedPose(pose, init, result.loss, keyframe)

    def inside_map(self, pf: PreparedFrame, extent: np.ndarray, pose: torch.Tensor) -> torch.Tensor:
        """Pixels whose depth point lies inside the map's extent: the field knows nothing beyond it."""
        depth = pf.depth.reshape(-1)
        return ~outside_mask(depth_points_world(self.dirs_cam, depth, pose), extent).reshape(pf.depth.shape)
