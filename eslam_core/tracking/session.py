"""A tracking session: one camera's tracking step, written once for every driver.

The front end (prediction, tracker, quality, keyframe decision), the trajectory it records into and the keyframes
it makes. The lock-step system (`slam.py`) and the tracking process (`runtime/workers.py`) drive the same session:
`first` for the frame that starts the map, `step` for every later one (`dead_reckon` for a live frame before the
first map), `new_keyframe` and `remember` once the pose is out, and `apply` for what mapping changed since: refined keyframe poses
and keyframes dropped from the store.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
import torch

from eslam_core.camera import Intrinsics
from eslam_core.config import Config
from eslam_core.frames import PreparedFrame
from eslam_core.mapping.keyframes import Keyframe
from eslam_core.mapping.scene_map import initial_extent
from eslam_core.tracking.frontend import MapView, TrackedPose, TrackingFrontEnd
from eslam_core.tracking.map_check import MapCheck
from eslam_core.trajectory import FrameRecord, TrackedTrajectory


@dataclass(frozen=True)
class PoseCorrections:
    """What a mapping step changed in the tracking's past: keyframe number -> refined (4, 4) pose, and the numbers
    of the keyframes the store dropped (relocalization no longer matches against them)."""
    refined: dict = field(default_factory=dict)
    dropped: tuple = ()


@dataclass
class Tracked:
    """One frame through the session: its trajectory record, and what the driver does next with it."""
    record: FrameRecord
    anchor: bool  # the record anchors the trajectory: a keyframe, or (localization) every frame
    keyframe_due: bool  # the front end made it a keyframe: make it (`new_keyframe`) once the pose is out
    pose: Optional[TrackedPose] = None  # the front end's result (None for the first frame)
    extent: Optional[np.ndarray] = None  # the first frame: the map's initial extent


def new_keyframe(pf: PreparedFrame, pose: torch.Tensor, number: int) -> Keyframe:
    return Keyframe.from_tensors(pf.index, pf.timestamp, pf.rgb, pf.depth, torch.ones_like(pf.depth, dtype=torch.bool),
                                 pose, number)


class TrackingSession:
    def __init__(self, cfg: Config, intr: Intrinsics, dirs_cam: torch.Tensor,
                 trajectory: Optional[TrackedTrajectory] = None, frontend: Optional[TrackingFrontEnd] = None):
        self.cfg = cfg
        self.intr = intr
        self.frontend = frontend if frontend is not None else TrackingFrontEnd(cfg, intr, dirs_cam)
        self.trajectory = trajectory if trajectory is not None else TrackedTrajectory()

    def first(self, pf: PreparedFrame) -> tuple[Tracked, Keyframe]:
        """The frame that starts the map: it fixes the map frame and the initial extent, and is keyframe 0 (to
        `remember` as any keyframe)."""
        pose0 = self.frontend.first_pose(pf, self.trajectory)
        extent = initial_extent(self.cfg, pf, self.intr, pose0)
        record = self.trajectory.record(pf.index, pf.timestamp, pose0, 0.0, pf.gt_pose, keyframe=True)
        kf = new_keyframe(pf, torch.from_numpy(pose0).float(), 0)
        return Tracked(record, True, False, extent=extent), kf

    def step(self, pf: PreparedFrame, view: MapView, catch_up: Optional[Callable[[], bool]] = None) -> Tracked:
        """Track a frame against `view` and record its pose (`TrackingFrontEnd.track`, `catch_up` included)."""
        tracked = self.frontend.track(pf, view, self.trajectory, catch_up)
        # Localization refines nothing: each frame is its own anchor (its pose as tracked).
        anchor = tracked.keyframe or self.cfg.run.mode == "localization"
        record = self.trajectory.record(pf.index, pf.timestamp, tracked.pose.double().numpy(), tracked.loss,
                                        pf.gt_pose, anchor, tracked.quality.value, tracked.lost,
                                        tracked.quality.degraded, tracked.covariance_matrix)
        return Tracked(record, anchor, tracked.keyframe, tracked)

    def dead_reckon(self, pf: PreparedFrame) -> Optional[Tracked]:
        """A live frame before the first map: its pose from the odometry alone (`TrackingFrontEnd.dead_reckon`),
        recorded; None where the odometry cannot pose it (the frame then waits for the map)."""
        reckoned = self.frontend.dead_reckon(pf, self.trajectory)
        if reckoned is None:
            return None
        record = self.trajectory.record(pf.index, pf.timestamp, reckoned.pose.double().numpy(), reckoned.loss,
                                        pf.gt_pose, False, reckoned.quality.value, False)
        return Tracked(record, False, False, reckoned)

    def new_keyframe(self, pf: PreparedFrame, tracked: Tracked) -> Keyframe:
        """The keyframe of a frame the front end chose, for the map; `remember` it too."""
        return new_keyframe(pf, tracked.pose.pose, tracked.record.reference)

    def remember(self, kf: Keyframe) -> None:
        """A new keyframe, for relocalization (after it went to the map: the mapper need not wait for indexing).
        The pipelined runtime's tracker does not: its mapper indexes the keyframes (places.py)."""
        self.frontend.remember(kf)

    @property
    def idle_work(self) -> bool:
        """New keyframes wait for their relocalization features or their map check (`index_next` while idle)."""
        return self.frontend.idle_work

    def index_next(self) -> bool:
        return self.frontend.index_next()

    def take_checks(self) -> list:
        """The map checks that placed a keyframe since the last call (with submaps: loop closure's candidates)."""
        places = self.frontend.places
        return [] if places is None else places.take_checks()

    @property
    def map_check(self) -> Optional[MapCheck]:
        """The newest check of the map against itself (map_check.py), None before one found a match."""
        return self.frontend.map_check

    def apply(self, corrections: PoseCorrections) -> None:
        """Mapping's corrections: every frame moves with its keyframe (trajectory.py), the front end predicts and
        relocalizes from the refined poses and forgets the dropped keyframes."""
        self.trajectory.refine(corrections.refined)
        self.frontend.refine(corrections.refined)
        self.frontend.forget(corrections.dropped)
