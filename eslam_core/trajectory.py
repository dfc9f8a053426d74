"""The trajectory: one record per tracked frame, its pose relative to the keyframe it was tracked after.

Mapping refines keyframe poses only. Every other frame is stored relative to its keyframe and moves with that
keyframe's correction, blended (by time) into the next keyframe's correction as it nears that keyframe
(`frame_pose`): tracking errors drift smoothly between keyframes, and mapping corrects them at the keyframes only.
The same class serves the lock-step system, the tracking process and the runtime's copy in the caller's process.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import torch

from eslam_core.geometry import interpolate_pose


@dataclass
class FrameRecord:
    index: int
    timestamp: float
    reference: int  # keyframe number (0, 1, ... in order of creation) this frame's pose is relative to
    relative: np.ndarray  # 4x4: pose = keyframe pose @ relative (before blending, see frame_pose)
    tracking_loss: float
    gt_pose: Optional[np.ndarray]
    tracked: np.ndarray  # 4x4: the pose when tracked (a keyframe's before mapping refined it)
    quality: float = 1.0  # of the tracked pose, in [0, 1] (tracking/quality.py)
    lost: bool = False  # the camera was lost at this frame: the pose is a guess


def frame_pose(records: list[FrameRecord], keyframe_records: dict[int, int], keyframe_pose: Callable[[int], np.ndarray],
               k: int) -> np.ndarray:
    """The pose of frame `k` given the keyframe poses as mapping has refined them (`keyframe_records`: keyframe
    number -> its record): its keyframe's correction blended by time into the next keyframe's."""
    r = records[k]
    own = keyframe_pose(r.reference) @ r.relative
    start, end = keyframe_records.get(r.reference), keyframe_records.get(r.reference + 1)
    if start is None or end is None or start == k:
        return own
    a, b = records[start], records[end]
    span = b.timestamp - a.timestamp
    t = float(np.clip((r.timestamp - a.timestamp) / span, 0.0, 1.0)) if span > 0 else 0.0
    with_next = keyframe_pose(r.reference + 1) @ np.linalg.inv(b.tracked) @ r.tracked
    return interpolate_pose(own, with_next, t)


class TrackedTrajectory:
    def __init__(self):
        self.records: list[FrameRecord] = []
        self.keyframe_records: dict[int, int] = {}  # keyframe number -> its own record
        self.keyframe_poses: dict[int, np.ndarray] = {}  # keyframe number -> pose as mapping refined it
        # poses() of earlier calls, per record, and the keyframes whose frames moved since: the node asks for every
        # pose every second, and recomputing them all took 0.7 s after 20 minutes at 30 Hz.
        self._cache = np.zeros((0, 4, 4))
        self._cached = np.zeros(0, bool)
        self._references = np.zeros(0, np.int64)
        self._moved: set[int] = set()

    def __len__(self) -> int:
        return len(self.records)

    @property
    def keyframes(self) -> int:
        return len(self.keyframe_records)

    def record(self, index: int, timestamp: float, pose: np.ndarray, loss: float, gt_pose: Optional[np.ndarray],
               keyframe: bool, quality: float = 1.0, lost: bool = False) -> FrameRecord:
        """Store a tracked frame relative to the newest keyframe (itself, when it is a new keyframe)."""
        pose = np.asarray(pose, dtype=np.float64)
        ref = self.keyframes if keyframe else self.keyframes - 1
        relative = np.eye(4) if keyframe else np.linalg.inv(self.keyframe_pose(ref)) @ pose
        rec = FrameRecord(index, timestamp, ref, relative, loss, gt_pose, pose, quality, lost)
        self.append(rec, keyframe)
        return rec

    def append(self, record: FrameRecord, keyframe: bool) -> None:
        """Add a record made elsewhere (by the tracking process). A keyframe's refinement may arrive before it."""
        if keyframe:
            self.keyframe_poses.setdefault(record.reference, np.asarray(record.tracked, dtype=np.float64))
            self.keyframe_records[record.reference] = len(self.records)
            self._moved.add(record.reference - 1)  # the previous keyframe's frames now blend into this one
        self.records.append(record)

    def refine(self, poses: dict) -> None:
        """Keyframe number -> refined 4x4 pose (numpy or torch)."""
        for i, pose in poses.items():
            self.keyframe_poses[int(i)] = np.asarray(pose, dtype=np.float64)
            self._moved.update((int(i), int(i) - 1))  # its own frames, and those blending into it

    def keyframe_pose(self, i: int) -> np.ndarray:
        return self.keyframe_poses[i]

    def pose(self, k: int) -> np.ndarray:
        return frame_pose(self.records, self.keyframe_records, self.keyframe_pose, k)

    def poses(self) -> np.ndarray:
        """Every frame's pose (N, 4, 4); only those whose keyframes moved since the last call are computed."""
        n, have = len(self.records), len(self._references)
        if n > have:
            self._references = np.concatenate([self._references, [r.reference for r in self.records[have:]]])
            self._cache = np.concatenate([self._cache, np.zeros((n - have, 4, 4))])
            self._cached = np.concatenate([self._cached, np.zeros(n - have, bool)])
        if self._moved:
            self._cached &= ~np.isin(self._references, list(self._moved))
            self._moved.clear()
        for k in np.flatnonzero(~self._cached):
            self._cache[k] = self.pose(int(k))
        self._cached[:] = True
        return self._cache.copy()

    def timestamps(self) -> np.ndarray:
        return np.array([r.timestamp for r in self.records])

    def gt_poses(self) -> list:
        return [r.gt_pose for r in self.records]

    # ------------------------------------------------------------------------------------------------ checkpoint
    def state_dict(self) -> dict:
        # Tensors, not numpy arrays, so that checkpoints load with torch.load(weights_only=True).
        return {
            "records": [dict(r.__dict__, relative=torch.from_numpy(r.relative), tracked=torch.from_numpy(r.tracked),
                             gt_pose=None if r.gt_pose is None else torch.from_numpy(r.gt_pose))
                        for r in self.records],
            "keyframe_poses": {int(i): torch.from_numpy(p) for i, p in self.keyframe_poses.items()},
        }

    @staticmethod
    def from_state_dict(state: dict) -> "TrackedTrajectory":
        traj = TrackedTrajectory()
        for r in state["records"]:
            traj.records.append(FrameRecord(**dict(r, relative=r["relative"].numpy(), tracked=r["tracked"].numpy(),
                                                   gt_pose=None if r["gt_pose"] is None else r["gt_pose"].numpy())))
        for k, r in enumerate(traj.records):
            traj.keyframe_records.setdefault(r.reference, k)
        traj.keyframe_poses = {int(i): p.numpy() for i, p in state["keyframe_poses"].items()}
        return traj
