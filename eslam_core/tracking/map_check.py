"""The map checked against itself (not part of the paper's method): catching a slide that is already mapped.

A view that leaves the pose free can let tracking slide along it with every residual small. Where that is not
caught (quality.py's degraded frames are not mapped), the slide's keyframes are mapped where the camera was
believed to be, and tracking against that map stays consistent with it: no residual tells. The camera's return to
a place mapped before the slide does: the features of the older keyframes place the newest keyframe where it is
relative to them, away from where it was tracked.

So each keyframe, once indexed for relocalization, is placed by the features of keyframes at least
`relocalization.map_check_gap` older (PnP, relocalization.py), within `relocalization.max_jump_m` of where it was
tracked (farther is another place that looks alike). The newest such placement is the map's check; the
map disagrees with itself while it lies more than `map_disagree_m` or `map_disagree_deg` from the tracked pose, and
until a later keyframe's placement agrees again the poses say so: their quality is capped, their covariance widened
by the disagreement, the health and status report it. Moving the later part of the map back is loop closure's job.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Generator, Optional

import numpy as np

from eslam_core.camera import Intrinsics
from eslam_core.config import RelocalizationConfig
from eslam_core.geometry import rotation_angle_deg
from eslam_core.tracking.information import PoseCovariance
from eslam_core.tracking.relocalization import plausible_jump


@dataclass(frozen=True)
class MapCheck:
    keyframe: int  # the keyframe placed
    by: int  # the older keyframe whose features placed it
    metres: float  # between the camera centres of the tracked and the placed pose
    degrees: float  # the turn between them
    disagrees: bool
    placed: Optional[np.ndarray] = None  # (4, 4) the keyframe's world pose as the older one places it

    @property
    def reason(self) -> str:
        return (f"the map disagrees with itself: keyframe {self.keyframe} was tracked {100 * self.metres:.0f} cm / "
                f"{self.degrees:.1f} deg from where keyframe {self.by}'s features place it (a slide mapped earlier)")


def check_map(places, number: int, tracked: np.ndarray, intr: Intrinsics,
              cfg: RelocalizationConfig) -> Generator[None, None, Optional[MapCheck]]:
    """Keyframe `number` (indexed in `places`, a KeyframeDatabase; `tracked` its 4x4 pose) placed by the features
    of the keyframes at least `cfg.map_check_gap` older; None where the check is off or none of them explains it.
    Done one candidate keyframe per step (KeyframeDatabase.placing): the generator returns the check."""
    if cfg.map_check_gap <= 0 or number < cfg.map_check_gap:
        return None
    found = yield from places.placing(number, intr, number - cfg.map_check_gap + 1)
    return None if found is None else compared(number, found.keyframe_id, found.pose, tracked, cfg)


def compared(number: int, by: int, placed: np.ndarray, tracked: np.ndarray, cfg: RelocalizationConfig
             ) -> Optional[MapCheck]:
    """Keyframe `number`, tracked at `tracked`, placed at `placed` by keyframe `by`'s features: the check, or None
    where the place is farther than `relocalization.max_jump_m` from the tracked pose. That is another place that
    looks alike, not a slide (as for a relocalization of a camera that is not lost): the generated flat's rooms
    share their furniture, and its keyframes were placed 2-8 m away and turned 90-180 degrees, the map said to
    disagree with itself every time."""
    if not plausible_jump(placed, tracked, cfg.max_jump_m):
        return None
    metres = float(np.linalg.norm(placed[:3, 3] - tracked[:3, 3]))
    degrees = rotation_angle_deg(placed[:3, :3].T @ tracked[:3, :3])
    return MapCheck(number, by, metres, degrees, metres > cfg.map_disagree_m or degrees > cfg.map_disagree_deg,
                    placed)


def widened(covariance: Optional[PoseCovariance], check: MapCheck) -> PoseCovariance:
    """A pose's covariance with the map's disagreement added to every position axis (as a standard deviation)."""
    matrix = np.zeros((6, 6)) if covariance is None else covariance.matrix.copy()
    matrix[:3, :3] += check.metres ** 2 * np.eye(3)
    return PoseCovariance(matrix, covariance is not None and covariance.free)
