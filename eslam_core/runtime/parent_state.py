"""What both runtimes keep on the caller's side (the parent of the workers, or the caller's thread beside the SLAM
thread): the trajectory as the tracker recorded it, moved by mapping's refinements (so that `trajectory()` needs no
round trip), the tags of the frames submitted and not yet posed (each comes back with its frame's pose), the pose
updates not yet polled, the tracking and mapping rates, the pose latency, and the newest frame's quality. Not
locked: each runtime holds its own lock around it."""
from __future__ import annotations

from typing import Any, Optional

from eslam_core.runtime.api import LatencyMeter, PoseUpdate, RateMeter
from eslam_core.trajectory import FrameRecord, TrackedTrajectory


class ParentState:
    def __init__(self, trajectory: Optional[TrackedTrajectory] = None):
        self.trajectory = trajectory if trajectory is not None else TrackedTrajectory()
        self.updates: list[PoseUpdate] = []
        self.tags: dict[int, Any] = {}  # frame index -> the submitted frame's tag, until its pose
        self.tracking_rate, self.mapping_rate, self.latency = RateMeter(), RateMeter(), LatencyMeter()
        self.last_quality = (1.0, False)  # the newest frame's quality, and whether the camera is lost there

    def submitted(self, index: int, tag: Any) -> None:
        if tag is not None:
            self.tags[index] = tag

    def posed(self, record: FrameRecord, anchor: bool, keyframe: bool, latency_s: float, done: float) -> None:
        """A frame's record from the tracker (`anchor`: it anchors the trajectory), and its pose update. The newest
        frame has no next keyframe to blend with: its pose is the pose as tracked."""
        self.trajectory.append(record, anchor)
        self.last_quality = (record.quality, record.lost)
        tag = self.tags.pop(record.index, None)
        if self.tags and min(self.tags) < record.index:  # frames the live policy dropped: no pose will come
            self.tags = {i: t for i, t in self.tags.items() if i > record.index}
        self.updates.append(PoseUpdate(record.index, record.timestamp, record.tracked, record.tracking_loss, keyframe,
                                       latency_s, record.quality, record.lost, record.degraded, record.covariance, tag))
        self.tracking_rate.tick(done)
        self.latency.add(latency_s)

    def mapped(self, refined: dict, done: float) -> None:
        """A mapping step's refined keyframe poses (keyframe number -> 4x4)."""
        self.trajectory.refine(refined)
        self.mapping_rate.tick(done)

    def corrected(self, refined: dict) -> None:
        """Keyframe poses moved by a loop closure (keyframe number -> 4x4)."""
        self.trajectory.refine(refined)

    def take_updates(self) -> list[PoseUpdate]:
        out, self.updates = self.updates, []
        return out

    def health_figures(self) -> dict:
        """The `Health` fields this state knows."""
        return dict(keyframes=self.trajectory.keyframes, tracking_hz=self.tracking_rate.rate(),
                    mapping_hz=self.mapping_rate.rate(), latency_ms_last=self.latency.last_ms,
                    latency_ms_mean=self.latency.mean_ms, tracking_quality=self.last_quality[0],
                    tracking_lost=self.last_quality[1])
