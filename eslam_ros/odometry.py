"""External odometry for the node: the robot's `odom -> base` pose at each image's stamp.

The odometry comes from a nav_msgs/Odometry topic (`OdometryBuffer`) or, on a ROS installation, from TF (see
eslam_ros.tf_chain.TfOdometry); both answer `lookup(stamp)` with an `OdomLookup`. Three things can go wrong, and
each is reported instead of hidden:

- *wait*: the image is newer than the newest odometry (odometry usually arrives a few ms after the image). The
  frame waits in `OdometryWait`. While the odometry is flowing (a newer sample came within WALL_GRACE_S seconds)
  it waits for it, up to MAX_LAG_S seconds of newer images: a node busy with its own work (a loaded CPU, the
  offline policy's back-pressure, an executor that happens to take several images before the odometry queued
  beside them) has not yet read the odometry waiting in its queue, and must not give up on it. Once the odometry
  has stalled, the frame waits until a frame `wait_s` seconds newer has arrived (or, at the end of a stream,
  `wait_s` + WALL_GRACE_S seconds of wall time passed), then goes on without odometry ("missing").
- *gap*: the odometry samples around the image stamp are more than `max_gap` seconds apart; an interpolation over
  such a hole is a guess, so the frame gets no odometry.
- *jump*: between two frames the odometry moved faster than `max_speed` / `max_angular_speed` (a reset of the
  wheel odometry, a relocalised VIO). `ContinuousOdometry` assumes no motion across the jump and keeps what it
  hands to SLAM continuous; the raw odometry still includes the jump, so `map -> odom` absorbs it, as REP 105
  intends (map -> odom is the correction of the odometry's discontinuities).

Poses are 4x4 matrices. Nothing here imports rclpy.
"""
from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass
from enum import Enum
from typing import Callable, Generic, Optional, TypeVar

import numpy as np

from eslam_core.geometry import interpolate_pose, relative_motion, rotation_angle_deg


class OdomStatus(str, Enum):
    MATCHED = "matched"
    WAIT = "wait"  # the stamp is newer than the newest odometry: ask again later
    GAP = "gap"  # the samples around the stamp are too far apart
    MISSING = "missing"  # no odometry covers the stamp (too old, none yet, or the wait ran out)


@dataclass(frozen=True)
class OdomLookup:
    status: OdomStatus
    pose: Optional[np.ndarray] = None  # odom -> base (4x4) at the stamp, when MATCHED
    message: str = ""  # what happened and what to check, when not MATCHED


class OdometryBuffer:
    """Recent odom -> base poses from an odometry topic, interpolated at image stamps.

    Keeps `history_s` seconds of samples. A stamp between two samples gets the pose interpolated between them
    (translation linear, rotation along the geodesic); a stamp equal to a sample (within `tolerance`) gets that
    sample. Samples whose stamps go back restart the buffer (the odometry was restarted or the bag looped).
    """

    def __init__(self, max_gap: float = 0.5, history_s: float = 10.0, tolerance: float = 1e-6) -> None:
        self.max_gap = max_gap
        self.history_s = history_s
        self.tolerance = tolerance
        self._stamps: list[float] = []
        self._poses: list[np.ndarray] = []
        self.samples = 0
        self.restarts = 0

    def add(self, stamp: float, pose: np.ndarray) -> None:
        if self._stamps and stamp < self._stamps[-1] - self.tolerance:
            self.clear()
            self.restarts += 1
        if self._stamps and abs(stamp - self._stamps[-1]) <= self.tolerance:
            self._poses[-1] = np.asarray(pose, dtype=np.float64)  # a repeated stamp: the newer value wins
            return
        self._stamps.append(stamp)
        self._poses.append(np.asarray(pose, dtype=np.float64))
        self.samples += 1
        old = bisect.bisect_left(self._stamps, stamp - self.history_s)
        if old > 0:
            del self._stamps[:old], self._poses[:old]

    def clear(self) -> None:
        self._stamps.clear()
        self._poses.clear()

    @property
    def newest(self) -> Optional[float]:
        return self._stamps[-1] if self._stamps else None

    def lookup(self, stamp: float) -> OdomLookup:
        if not self._stamps:
            return OdomLookup(OdomStatus.WAIT, message="no odometry received yet")
        first, last = self._stamps[0], self._stamps[-1]
        if stamp > last + self.tolerance:
            return OdomLookup(OdomStatus.WAIT, message=f"newest odometry is {stamp - last:.3f} s older than the image")
        if stamp < first - self.tolerance:
            return OdomLookup(OdomStatus.MISSING, message=(
                f"the image (stamp {stamp:.3f}) is older than the odometry kept ({first:.3f} .. {last:.3f}); are "
                f"odometry and camera stamped by the same clock (use_sim_time)?"))
        i = bisect.bisect_left(self._stamps, stamp)
        for j in (i - 1, i):  # a sample at the stamp itself
            if 0 <= j < len(self._stamps) and abs(self._stamps[j] - stamp) <= self.tolerance:
                return OdomLookup(OdomStatus.MATCHED, self._poses[j].copy())
        t0, t1 = self._stamps[i - 1], self._stamps[i]
        if t1 - t0 > self.max_gap:
            return OdomLookup(OdomStatus.GAP, message=(
                f"odometry has a gap of {t1 - t0:.3f} s around the image stamp (more than odom.max_gap = "
                f"{self.max_gap} s)"))
        return OdomLookup(OdomStatus.MATCHED, interpolate_pose(self._poses[i - 1], self._poses[i],
                                                               (stamp - t0) / (t1 - t0)))


Item = TypeVar("Item")
# Wall-clock seconds beyond `wait_s` after which a frame stops waiting even if no newer frame came (end of stream);
# also how recent the last odometry sample must be for the odometry to count as flowing.
WALL_GRACE_S = 1.0
# Seconds of newer images after which a frame stops waiting even for a flowing odometry: no robot's odometry is this
# late, and the frames waiting meanwhile are held in memory.
MAX_LAG_S = 1.0


class OdometryWait(Generic[Item]):
    """Frames waiting for the odometry at their stamp, released in arrival order.

    `push` a frame with its stamp, tell `odometry_arrived(now)` whenever an odometry sample came, then
    `release(now)` returns (frame, lookup) for every frame at the head of the queue whose odometry is known, or
    whose wait ran out (then MISSING, with the reason): MAX_LAG_S seconds of newer images are queued behind it, or
    the odometry stalled (no sample for WALL_GRACE_S seconds) and a frame `wait_s` seconds newer is queued or
    `wait_s + WALL_GRACE_S` seconds passed. Order is kept: a frame never overtakes an older one.
    """

    def __init__(self, lookup: Callable[[float], OdomLookup], wait_s: float = 0.1) -> None:
        self.lookup = lookup
        self.wait_s = wait_s
        self._queue: deque[tuple[float, float, Item]] = deque()
        self._last_arrival: Optional[float] = None

    def __len__(self) -> int:
        return len(self._queue)

    def push(self, stamp: float, item: Item, now: float) -> None:
        self._queue.append((stamp, now, item))

    def odometry_arrived(self, now: float) -> None:
        self._last_arrival = now

    def release(self, now: float, flush: bool = False) -> list[tuple[Item, OdomLookup]]:
        """`flush`: the end of the stream, nothing more will come: release everything."""
        out = []
        flowing = self._last_arrival is not None and now - self._last_arrival < WALL_GRACE_S
        while self._queue:
            stamp, since, item = self._queue[0]
            result = self.lookup(stamp)
            if result.status == OdomStatus.WAIT:
                newest = self._queue[-1][0]
                ahead = newest - stamp + 1e-9  # stamps are floats: a nanosecond of slack
                stalled = not flowing and (ahead >= self.wait_s or now - since >= self.wait_s + WALL_GRACE_S)
                if not (flush or ahead >= MAX_LAG_S or stalled):
                    break
                result = OdomLookup(OdomStatus.MISSING, message=(
                    f"no odometry for the image stamp {stamp:.3f} after waiting {now - since:.2f} s, "
                    f"{newest - stamp:.2f} s of images ({result.message}"
                    f"{'; the odometry is flowing but late' if flowing else ''})"))
            self._queue.popleft()
            out.append((item, result))
        return out

    def clear(self) -> list[Item]:
        items = [item for _, _, item in self._queue]
        self._queue.clear()
        return items


def is_jump(previous: np.ndarray, current: np.ndarray, dt: float, max_speed: float,
            max_angular_speed: float) -> bool:
    """The motion from `previous` to `current` in `dt` seconds is faster than a robot moves (m/s, rad/s)."""
    motion = relative_motion(previous, current)
    distance = float(np.linalg.norm(motion[:3, 3]))
    angle = math.radians(rotation_angle_deg(motion[:3, :3]))
    dt = max(dt, 1e-6)
    return distance / dt > max_speed or angle / dt > max_angular_speed


class ContinuousOdometry:
    """The odometry as SLAM gets it: the raw odom -> base poses with their jumps taken out.

    `correction` (4x4) is applied on the left of every raw pose; after a jump it changes so that the pose after the
    jump equals the pose before it (no motion assumed across the jump). `step(stamp, raw)` returns the continuous
    pose and whether this frame came after a jump.
    """

    def __init__(self, max_speed: float = 5.0, max_angular_speed: float = 6.0) -> None:
        self.max_speed = max_speed
        self.max_angular_speed = max_angular_speed
        self.correction = np.eye(4)
        self.jumps = 0
        self._last: Optional[tuple[float, np.ndarray]] = None  # (stamp, raw pose) of the previous frame

    def step(self, stamp: float, raw: np.ndarray) -> tuple[np.ndarray, bool]:
        jumped = False
        if self._last is not None:
            t_prev, raw_prev = self._last
            if is_jump(raw_prev, raw, stamp - t_prev, self.max_speed, self.max_angular_speed):
                self.correction = self.correction @ raw_prev @ np.linalg.inv(raw)
                self.jumps += 1
                jumped = True
        self._last = (stamp, raw)
        return self.correction @ raw, jumped

    def reset(self) -> None:
        """A new map: the odometry is taken as it comes again."""
        self.correction = np.eye(4)
        self._last = None

