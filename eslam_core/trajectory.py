"""The trajectory: one record per tracked frame, its pose relative to the keyframe it was tracked after.

Mapping refines keyframe poses only. Every other frame is stored relative to its keyframe and moves with that
keyframe's correction, blended (by time) into the next keyframe's correction as it nears that keyframe
(`frame_pose`): tracking errors drift smoothly between keyframes, and mapping corrects them at the keyframes only.
The same class serves the lock-step system, the tracking process and the runtime's copy in the caller's process.

`Trajectory` is the plain sequence of time stamps and poses that is written to a file (datasets/tum.py) and compared
with the ground truth (evaluation/trajectory_error.py).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from eslam_core.geometry import interpolate_pose


class TrajectoryError(ValueError):
    """A trajectory that cannot be read or compared (malformed file, non-finite pose, no common timestamps)."""


@dataclass(frozen=True, eq=False)
class Trajectory:
    timestamps: np.ndarray  # (N,) seconds (or frame numbers for data sets without a clock)
    poses: np.ndarray  # (N, 4, 4) camera-to-world

    def __post_init__(self) -> None:
        timestamps = np.asarray(self.timestamps, dtype=np.float64)
        poses = np.asarray(self.poses, dtype=np.float64)
        if timestamps.ndim != 1 or poses.shape != (len(timestamps), 4, 4):
            raise TrajectoryError(
                f"a trajectory needs N timestamps and N 4x4 poses, got {timestamps.shape} and {poses.shape}"
            )
        bad = np.flatnonzero(~(np.isfinite(poses).all(axis=(1, 2)) & np.isfinite(timestamps)))
        if bad.size:
            raise TrajectoryError(
                f"pose at timestamp {float(timestamps[bad[0]])!r} is not finite (nan/inf); {bad.size} such poses: "
                "the estimator lost track there, remove or fix those poses"
            )
        object.__setattr__(self, "timestamps", timestamps)
        object.__setattr__(self, "poses", poses)

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]


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
    degraded: bool = False  # the view left the pose free in some direction (tracking/quality.py)
    covariance: Optional[np.ndarray] = None  # (6, 6) of the tracked pose, x y z roll pitch yaw; None: not measured


def frame_pose(records: Sequence[FrameRecord], keyframe_records: dict[int, int],
               keyframe_pose: Callable[[int], np.ndarray], k: int) -> np.ndarray:
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


def thinned(n: int, max_poses: Optional[int]) -> np.ndarray:
    """Positions of n records to show at most `max_poses` of them (None: all): every s-th and the newest, s the
    smallest power of two that fits, so that a position shown stays shown until s doubles (a path published
    again and again over hours of frames then costs the same every time, and changes little between two)."""
    if max_poses is None or n <= max_poses:
        return np.arange(n)
    stride = 1 << int(np.ceil(np.log2(n / max(max_poses - 1, 1))))
    picked = np.arange(0, n, stride)
    return picked if picked[-1] == n - 1 else np.append(picked, n - 1)


def _grown(a: np.ndarray, n: int) -> np.ndarray:
    """`a` with room for at least n rows along its first axis: doubled, so appending one at a time is O(1) each."""
    if len(a) >= n:
        return a
    out = np.zeros((max(2 * len(a), n, 256),) + a.shape[1:], a.dtype)
    out[:len(a)] = a
    return out


class _Columns:
    """The records of a trajectory as growable arrays. Poses are kept in float32: a tracked pose comes from float32
    tensors, and a relative pose rounded to float32 moves a frame by under a micrometre at 10 m. About 390 bytes a
    frame (three 4x4 poses, a 6x6 covariance, seven scalars), where FrameRecords holding three float64 4x4 arrays
    took 1.2 KB. `essential`: only what tracking reads back (the time stamp, the keyframe and the two poses: 150
    bytes), as the tracking process keeps it; its records go whole to the caller's copy."""

    POSES = ("relative", "tracked", "gt_pose")
    SCALARS = {"index": np.int64, "timestamp": np.float64, "reference": np.int64, "tracking_loss": np.float64,
               "quality": np.float64, "lost": np.bool_, "degraded": np.bool_}
    ESSENTIAL = ("index", "timestamp", "reference", "relative", "tracked")
    NOT_MEASURED = {"gt_pose": np.nan, "covariance": np.nan, "tracking_loss": np.nan, "quality": 1.0, "lost": False,
                    "degraded": False}  # (what a column not kept, or not in an older checkpoint, reads as)

    def __init__(self, capacity: int = 256, essential: bool = False):
        self.n = 0
        self.arrays = {name: np.zeros((capacity, 4, 4), np.float32) for name in self.POSES}
        self.arrays["covariance"] = np.zeros((capacity, 6, 6), np.float32)
        self.arrays.update({name: np.zeros(capacity, dtype) for name, dtype in self.SCALARS.items()})
        if essential:
            self.arrays = {name: self.arrays[name] for name in self.ESSENTIAL}

    def append(self, r: FrameRecord) -> None:
        # (np.zeros: the new half is not resident until written)
        self.arrays = {name: _grown(a, self.n + 1) for name, a in self.arrays.items()}
        k, a = self.n, self.arrays
        for name, column in a.items():
            value = getattr(r, name)
            column[k] = self.NOT_MEASURED[name] if value is None else value
        self.n += 1

    def of(self, columns: dict) -> "_Columns":
        """Records of this kind from whole columns (a checkpoint's)."""
        n = len(columns["index"])
        self.arrays = {name: np.array(columns[name], dtype=a.dtype) if name in columns else
                       np.full((n,) + a.shape[1:], self.NOT_MEASURED[name], a.dtype) for name, a in self.arrays.items()}
        self.n = n
        return self

    def column(self, name: str) -> np.ndarray:
        return self.arrays[name][:self.n]

    def __getitem__(self, k: int) -> FrameRecord:
        if not -self.n <= k < self.n:
            raise IndexError(f"record {k} of {self.n}")
        k %= self.n
        a = self.arrays
        value = {**self.NOT_MEASURED, **{name: column[k] for name, column in a.items()}}

        def matrix(name: str) -> Optional[np.ndarray]:
            m = np.asarray(value[name], np.float64)
            return None if np.isnan(m.flat[0]) else m

        return FrameRecord(int(value["index"]), float(value["timestamp"]), int(value["reference"]),
                           matrix("relative"), float(value["tracking_loss"]), matrix("gt_pose"), matrix("tracked"),
                           float(value["quality"]), bool(value["lost"]), bool(value["degraded"]),
                           matrix("covariance"))

    def __len__(self) -> int:
        return self.n

    def __iter__(self):
        return (self[k] for k in range(self.n))


class TrackedTrajectory:
    def __init__(self, essential: bool = False):
        """`essential`: keep only what tracking reads back of each record (see _Columns)."""
        self.records = _Columns(essential=essential)  # records[k] is frame k's FrameRecord (made on access)
        self.keyframe_records: dict[int, int] = {}  # keyframe number -> its own record
        self.keyframe_poses: dict[int, np.ndarray] = {}  # keyframe number -> pose as mapping refined it
        # poses() of earlier calls, per record, and the keyframes whose frames moved since: the node asks for the
        # path every second, and recomputing every pose took 0.7 s after 20 minutes at 30 Hz.
        self._cache = np.zeros((0, 4, 4))
        self._cached = np.zeros(0, bool)  # (rows past len(self.records) are room to grow)
        self._moved: set[int] = set()

    def __len__(self) -> int:
        return len(self.records)

    @property
    def keyframes(self) -> int:
        return len(self.keyframe_records)

    def record(self, index: int, timestamp: float, pose: np.ndarray, loss: float, gt_pose: Optional[np.ndarray],
               keyframe: bool, quality: float = 1.0, lost: bool = False, degraded: bool = False,
               covariance: Optional[np.ndarray] = None) -> FrameRecord:
        """Store a tracked frame relative to the newest keyframe (itself, when it is a new keyframe)."""
        pose = np.asarray(pose, dtype=np.float64)
        ref = self.keyframes if keyframe else self.keyframes - 1
        relative = np.eye(4) if keyframe else np.linalg.inv(self.keyframe_pose(ref)) @ pose
        rec = FrameRecord(index, timestamp, ref, relative, loss, gt_pose, pose, quality, lost, degraded, covariance)
        self.append(rec, keyframe)
        return rec

    def append(self, record: FrameRecord, keyframe: bool) -> None:
        """Add a record made elsewhere (by the tracking process). A keyframe's refinement may arrive before it."""
        if keyframe:
            self.keyframe_poses.setdefault(record.reference, np.asarray(record.tracked, dtype=np.float64))
            self.keyframe_records[record.reference] = len(self.records)
            self._mark_moved(record.reference - 1)  # the previous keyframe's frames now blend into this one
        self.records.append(record)

    def refine(self, poses: dict) -> None:
        """Keyframe number -> refined 4x4 pose (numpy or torch)."""
        for i, pose in poses.items():
            self.keyframe_poses[int(i)] = np.asarray(pose, dtype=np.float64)
            self._mark_moved(int(i), int(i) - 1)  # its own frames, and those blending into it

    def _mark_moved(self, *keyframes: int) -> None:
        if len(self._cache):  # (nothing is cached before the first poses(): a tracker never asks, and never grows it)
            self._moved.update(keyframes)

    def keyframe_pose(self, i: int) -> np.ndarray:
        return self.keyframe_poses[i]

    def pose(self, k: int) -> np.ndarray:
        return frame_pose(self.records, self.keyframe_records, self.keyframe_pose, k)

    def poses(self, max_poses: Optional[int] = None) -> np.ndarray:
        """The frames' poses (N, 4, 4), or those of `thinned(N, max_poses)`; only those whose keyframes moved
        since they were last asked for are computed."""
        n = len(self.records)
        self._cache, self._cached = _grown(self._cache, n), _grown(self._cached, n)
        if self._moved:
            self._cached[:n] &= ~np.isin(self.records.column("reference"), list(self._moved))
            self._moved.clear()
        picked = thinned(n, max_poses)
        for k in picked[~self._cached[picked]]:
            self._cache[k] = self.pose(int(k))
        self._cached[picked] = True
        return self._cache[picked]

    def timestamps(self, max_poses: Optional[int] = None) -> np.ndarray:
        return self.records.column("timestamp")[thinned(len(self.records), max_poses)]

    def gt_poses(self) -> list:
        return [r.gt_pose for r in self.records]

    # ------------------------------------------------------------------------------------------------ checkpoint
    def state_dict(self) -> dict:
        # Tensors, not numpy arrays, so that checkpoints load with torch.load(weights_only=True).
        return {
            "records": {name: torch.from_numpy(self.records.column(name).copy()) for name in self.records.arrays},
            "keyframe_poses": {int(i): torch.from_numpy(p) for i, p in self.keyframe_poses.items()},
        }

    @staticmethod
    def from_state_dict(state: dict, essential: bool = False) -> "TrackedTrajectory":
        traj = TrackedTrajectory(essential)
        traj.records.of({name: c.numpy() for name, c in state["records"].items()})
        for k, reference in enumerate(traj.records.column("reference")):
            traj.keyframe_records.setdefault(int(reference), k)
        traj.keyframe_poses = {int(i): p.numpy() for i, p in state["keyframe_poses"].items()}
        return traj
