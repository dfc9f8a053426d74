"""The runtime API: how a caller (the offline runner, the ROS node) drives SLAM without waiting for it.

A runtime takes frames (`submit`), hands back poses as they are tracked (`poll`), and can at any time give the
trajectory, a checkpoint or a mesh of the map so far. Two implementations share this API:

- `InProcessRuntime` (workers=1): the lock-step `SLAM` on a background thread of the caller's process.
- `MultiProcessRuntime` (workers=2): a tracking process and a mapping process working at the same time.

Input policies decide what happens when frames arrive faster than they can be tracked:

- "offline": every frame is processed, in order; `submit` blocks while the input buffer is full.
- "live": `submit` never blocks; a full buffer loses its oldest pending frame, and the tracker takes the oldest
  pending frame while at most `runtime.live_backlog` more wait behind it, else the newest, skipping the older ones
  (`frames_to_skip`). Every frame lost either way is counted in `Health.frames_dropped`.
"""
from __future__ import annotations

import math
import resource
import time
from collections import deque
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Optional, Protocol, runtime_checkable

import numpy as np

from eslam_core.camera import Frame, Intrinsics

POLICIES = ("offline", "live")


class RuntimeSetupError(ValueError):
    """The runtime was asked for something it cannot do (unknown policy, bad worker count, wrong frame size)."""


class RuntimeCrashed(RuntimeError):
    """A worker died. `worker` names it, `traceback` is its traceback (or how it died), `summary` one line."""

    def __init__(self, worker: str, summary: str, traceback: str = ""):
        self.worker = worker
        self.summary = summary
        self.traceback = traceback
        super().__init__(f"{summary}\n{traceback}".rstrip())


@dataclass
class PoseUpdate:
    index: int
    timestamp: float
    pose: np.ndarray  # 4x4 camera-to-world, as tracked (later keyframe refinements show in `trajectory()`)
    tracking_loss: float
    keyframe: bool
    latency_s: float  # frame arrival (submit) -> pose available
    quality: float = 1.0  # of the tracked pose, in [0, 1] (tracking/quality.py)
    lost: bool = False  # the camera is lost: the pose is a guess (not mapped; a publisher should say so)
    degraded: bool = False  # the view leaves the pose free in some direction (not mapped; tracking/quality.py)
    covariance: Optional[np.ndarray] = None  # (6, 6) x y z roll pitch yaw, world frame; None: not measured
    tag: Any = None  # the submitted Frame's tag


@dataclass
class Health:
    frames_received: int
    frames_tracked: int
    frames_dropped: int
    keyframes: int
    tracking_hz: float  # tracked frames per second over the last few seconds
    mapping_hz: float  # mapping steps per second over the last few seconds
    input_queue_depth: int  # frames submitted and not yet taken by the tracker
    keyframe_queue_depth: int  # keyframes handed to the mapper and not yet mapped
    map_version: int  # increases whenever the tracker can see a newer map
    latency_ms_last: float
    latency_ms_mean: float  # over the last LATENCY_WINDOW poses
    # The cost of keeping tracker and mapper consistent (multi-process only; 0 otherwise), mean per call.
    map_publish_ms: float = 0.0
    map_read_ms: float = 0.0
    # The newest tracked frame's quality (tracking/quality.py), and whether the camera is lost.
    tracking_quality: float = 1.0
    tracking_lost: bool = False
    # Where memory goes: the map's parameters, the keyframe store (bounded by mapping.keyframe_budget_mb), the
    # keyframes it holds, and the peak resident memory of each process of the runtime (MB).
    map_bytes: int = 0
    keyframe_bytes: int = 0
    keyframes_kept: int = 0
    peak_memory_mb: dict = field(default_factory=dict)
    # Depth consistency of the newest keyframe with older ones under the current poses (needs no ground truth;
    # mapping/consistency.py): median |depth residual| in mm and the share within 3 cm; NaN before two keyframes.
    consistency_mm: float = math.nan
    consistency_agree: float = math.nan
    # The newest check of the map against itself (tracking/map_check.py): how far the newest keyframe placed by
    # older keyframes' features lies from where it was tracked (cm; NaN before a check found a match), and whether
    # that is a disagreement (a slide mapped earlier).
    map_disagreement_cm: float = math.nan
    map_disagrees: bool = False
    # The submaps of the map (submaps/atlas.py; 1: one map), the loops closed between them, and for the newest loop
    # the seconds of input from the revisit (the keyframe that found the place) to the corrected map (NaN: none).
    submaps: int = 1
    loops_closed: int = 0
    loop_correction_s: float = math.nan
    # Where the workers' time goes: milliseconds per event of each stage (runtime/shared.py: STAGES; multi-process).
    stage_ms: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return asdict(self)


@runtime_checkable
class SLAMRuntime(Protocol):
    def start(self) -> None: ...

    def submit(self, frame: Frame) -> None: ...

    def poll(self, timeout: float = 0.0) -> list[PoseUpdate]:
        """The poses tracked since the last call, oldest first; waits up to `timeout` seconds when there is none
        yet (a publisher thread that sends each pose as soon as it is made)."""

    def trajectory(self, max_poses: Optional[int] = None) -> tuple[np.ndarray, np.ndarray]:
        """Time stamps (N,) and poses (N, 4, 4) of the tracked frames, refined keyframe poses written back; with
        `max_poses`, at most that many (`trajectory.thinned`: evenly spread, the newest frame always)."""

    def health(self) -> Health: ...

    def mesh_snapshot(self, have: set):
        """What the mesh process needs of the current map (runtime/mesher.py: a MeshSnapshot, or the
        PackedSnapshot of one made in another process): the field, the
        keyframe poses and the depth images of the keyframes whose ids are not in `have`. Much lighter than
        `snapshot()` (no keyframe images, no trajectory); raises EmptyMeshError before the first keyframe."""

    def save_checkpoint(self, path) -> Path: ...

    def save_mesh(self, path, resolution: float | None = None) -> Path: ...

    def save_trajectory(self, path) -> Path: ...

    def reset(self) -> None: ...

    def close(self, timeout: float | None = None) -> None: ...

    def __enter__(self) -> "SLAMRuntime": ...

    def __exit__(self, *exc) -> None: ...


def peak_rss_mb() -> float:
    """Peak resident memory of this process (ru_maxrss is KiB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def frames_to_skip(pending: int, live: bool, backlog: int) -> int:
    """Of `pending` frames, how many the tracker skips before the one it takes: none offline, or live while at
    most `backlog` wait behind the oldest; else all but the newest. A live tracker with a few milliseconds of slack
    a frame that one frame's extra work (a keyframe handed over, a new map folded) made late catches up over the
    next frames instead of losing one; each frame that waited is a frame period later."""
    return pending - 1 if live and pending - 1 > backlog else 0


def check_policy(policy: str) -> str:
    if policy not in POLICIES:
        raise RuntimeSetupError(f"unknown input policy {policy!r}: choose one of {', '.join(POLICIES)} "
                                f"(offline = every frame in order, live = skip to the newest frame when behind)")
    return policy


def check_frame(frame: Frame, intrinsics: Intrinsics) -> None:
    """Refuse a frame at `submit`, in the caller's thread, rather than failing later inside a worker."""
    want = (intrinsics.height, intrinsics.width)
    if frame.rgb.shape[:2] != want or frame.depth.shape != want or frame.rgb.ndim != 3:
        raise RuntimeSetupError(
            f"frame {frame.index}: rgb {frame.rgb.shape} / depth {frame.depth.shape} do not match the camera "
            f"{intrinsics.width}x{intrinsics.height} the runtime was made for; give make_runtime the intrinsics of "
            f"these images (or fix the camera section of the config)")


# ------------------------------------------------------------------------------------------------- health figures

RATE_WINDOW_S = 10.0
LATENCY_WINDOW = 100


class RateMeter:
    """Events per second over the last `window_s` seconds."""

    def __init__(self, window_s: float = RATE_WINDOW_S):
        self.window_s = window_s
        self.times: deque = deque()

    def tick(self, t: float) -> None:
        self.times.append(t)
        self._forget(t)  # (a caller that never asks for the rate must not keep every event of the run)

    def _forget(self, now: float) -> None:
        while self.times and self.times[0] < now - self.window_s:
            self.times.popleft()

    def rate(self, now: Optional[float] = None) -> float:
        """Intervals between the recent events over the time since the oldest of them: the event rate while events
        come, decaying towards 0 when they stop."""
        now = time.monotonic() if now is None else now
        self._forget(now)
        if len(self.times) < 2:
            return 0.0
        return (len(self.times) - 1) / max(now - self.times[0], 1e-6)


class LatencyMeter:
    def __init__(self, window: int = LATENCY_WINDOW):
        self.recent: deque = deque(maxlen=window)

    def add(self, seconds: float) -> None:
        self.recent.append(seconds)

    @property
    def last_ms(self) -> float:
        return 1000.0 * self.recent[-1] if self.recent else 0.0

    @property
    def mean_ms(self) -> float:
        return 1000.0 * float(np.mean(self.recent)) if self.recent else 0.0
