"""Tracking quality: how much a tracked pose can be trusted, from what the tracker measured at that pose.

A tracked frame gives these pieces of evidence, each turned into a score in [0, 1]:
- depth: the fraction of pixels (inside the border) with a depth measurement. A covered lens, a sensor facing the
  sky or pressed against a wall has almost none, and no tracker can place it.
- inliers: the fraction of the scored depth points that land on the mapped surface at the returned pose, i.e.
  within the truncation distance T of it (SDF tracker: |T phi_g(x)| < T and the point in observed space;
  rendering tracker: |rendered depth - measured depth| < T). Measured on the synthetic room: 0.97-1.0 on tracked
  frames, 0.07-0.40 when the camera had jumped 20-50 cm / 10-20 degrees and the tracker settled elsewhere.
- residual: the tracker's loss against the typical loss of recently tracked frames (the loss scale differs between
  trackers and presets, its ratio does not): 1.0-1.1 on tracked frames, 6-13 after a jump.
- motion: the correction the tracker applied to the constant-velocity prediction, against what a hand-held camera
  does in one frame gap. Tracking can recover a correct pose 10 cm from the prediction, so this only flags
  corrections well beyond that.
- mapped (only while the camera is lost): the fraction of the depth points in observed space. The inlier score
  counts only those, which is right for a tracked camera looking at new space, but a lost camera tracked from a
  guess can settle where a quarter of its points fit some mapped surface and the rest lie in unmapped space.
- start (only while lost): whether the tracker started from a pose worth refining: a relocalization match, the
  odometry, or a pose tracked in this run. From where a loaded map ended it settles on whatever surface is near,
  which on 7-Scenes restarts were poses 1-4 m off with a quarter to half of their points fitting the map.
- constraint: the pose covariance (information.py). A view that leaves a direction free (a wall, two planes, a
  corridor) gives a pose that may be fine or may have slid along it, and nothing in the residuals tells which:
  where the frame leaves a direction free and the covariance's largest position or rotation axis exceeds
  `degraded_sigma_m` / `degraded_sigma_deg`, the frame is *degraded*: its quality is capped below `found_above`,
  it makes no keyframe, and the reason names the free direction. A pose constrained in every direction is not
  degraded however wide its covariance (real depth noise: published, and mapped), unless a direction is only
  weakly constrained and the pose moved along it by over a centimetre beyond the constant velocity: that change
  of motion is the odometry's guess (`weak_view`). Unless the view itself pins the pose down
  (information.view_information, its own surfaces' information) and only the map does not yet: a camera walking
  into a room sees floor, corner and furniture that settled space (observed.py) does not hold yet, and aligned to
  the two walls it does hold, the pose is free along them. Such a frame is not degraded: its quality is capped
  likewise, but it is mapped (else the map never learns the view, and the generated flat's camera walked on,
  degraded for 150 frames, out of the map and was lost), and the odometry, which registered the whole view, keeps
  its motion along the free direction.
- anchor: after a run of frames whose view left a direction free, the pose may have slid along it, and a
  constrained view does not undo that: a local tracker started tens of centimetres off settles where the view fits
  the map well enough (the generated corridor: back on the furniture 21 cm off, every point on the map). Such a
  pose is *unanchored* (frontend.py) until the keyframes place the camera again: degraded like the run before it.
- map: whether the map disagrees with itself (map_check.py: a slide mapped earlier). The pose may be right against
  the newer part of the map and wrong against the older: its quality is capped like a degraded frame's, but
  mapping goes on (the view itself is fine).
The quality is the weakest score (one bad piece of evidence is enough to distrust a pose), and the reason names it.
A frame is *lost* below `lost_below`; a lost camera counts as found again only at `found_above` (hysteresis, so
that a marginal frame does not flip the state back and forth).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from eslam_core.config import QualityConfig
from eslam_core.geometry import rotation_angle_deg
from eslam_core.tracking.information import WEAK_BELOW, PoseCovariance


@dataclass(frozen=True)
class TrackingEvidence:
    """What the tracker measured at the pose it returned (see the module docstring for each field)."""

    depth_fraction: float  # pixels with depth inside the border / pixels inside the border
    inlier_fraction: float  # scored points on the mapped surface at the returned pose / scored points
    observed_fraction: float  # scored points in observed space / scored points (NaN if unknown); for the reason
    loss: float  # the tracker's best loss (NaN if it did not run)
    correction: np.ndarray  # (4, 4) inv(predicted pose) @ returned pose
    typical_loss: Optional[float] = None  # median loss of recent tracked frames; None = no residual score yet
    gap_ratio: float = 1.0  # the time since the previous frame in units of the usual frame gap (prediction's)
    lost_before: bool = False  # the camera was lost at the previous frame: the pose must show it is in the map
    anchored: bool = True  # while lost: the tracker started from a relocalization, the odometry or a tracked pose
    covariance: Optional[PoseCovariance] = None  # of the returned pose (None: not measured)
    map_disagrees: Optional[str] = None  # the map disagrees with itself (map_check.py): why
    unanchored: Optional[str] = None  # the pose may still be off along what earlier views left free: why
    unexplained: Optional[np.ndarray] = None  # (3,) world move of the pose beyond the constant velocity's
    # The pose agrees with the frame-to-frame odometry's motion from the last well-tracked frame (odometry.py: it
    # registers the frames, not the map): the camera moved as tracked, whatever the loss says.
    odometry_agrees: bool = False
    # The frame's own geometry pins the pose down in every direction (information.view_information): a pose that
    # the map leaves free lacks map, not view.
    view_constrains: bool = False


@dataclass(frozen=True)
class Quality:
    value: float  # in [0, 1]
    reason: str  # what limits it ("ok" when nothing does)
    lost: bool  # value < lost_below
    degraded: bool = False  # the pose may be off along a direction a view left free (this one, or earlier ones)


def ramp(x: float, zero_at: float, one_at: float) -> float:
    """0 at `zero_at`, 1 at `one_at`, linear between, clamped (either direction)."""
    return float(min(1.0, max(0.0, (x - zero_at) / (one_at - zero_at))))


def tracking_quality(e: TrackingEvidence, cfg: Optional[QualityConfig] = None) -> Quality:
    """The quality of one tracked frame (pure: the frame's evidence only; see is_lost for the state). A fraction
    that is NaN (the tracker did not measure it) gives no score."""
    cfg = cfg or QualityConfig()
    if not math.isfinite(e.loss):
        depth = f"{100 * e.depth_fraction:.0f}%" if math.isfinite(e.depth_fraction) else "too few"
        return Quality(0.0, f"not tracked: {depth} of the pixels have depth", True)
    move_m = float(np.linalg.norm(e.correction[:3, 3]))
    move_deg = rotation_angle_deg(e.correction[:3, :3])
    gap = max(e.gap_ratio, 1.0)
    overshoot = max(move_m / (cfg.correction_m * gap), move_deg / (cfg.correction_deg * gap))
    scores = {"motion": (1.0 - ramp(overshoot, 1.0, 2.0),
                         f"the tracker moved the predicted pose by {100 * move_m:.0f} cm / {move_deg:.0f} deg")}
    if math.isfinite(e.depth_fraction):
        scores["depth"] = (ramp(e.depth_fraction, cfg.depth_low, cfg.depth_high),
                           f"{100 * e.depth_fraction:.0f}% of the pixels have depth (lens covered or out of range?)")
    if math.isfinite(e.inlier_fraction):
        scores["inliers"] = (ramp(e.inlier_fraction, cfg.inliers_low, cfg.inliers_high),
                             f"{100 * e.inlier_fraction:.0f}% of the depth points lie on the map"
                             + _observed_note(e.observed_fraction))
    # A high loss alone is not enough: on ICL-NUIM replayed back and forth, well-tracked frames of well-mapped space
    # reached 9-15x the recent loss. It counts when the points also leave observed space (a jump: 42 % observed).
    # A tracker that does not measure observed space (the rendering tracker: NaN) gives no residual score: its loss
    # covers rays into unmapped space too, and rose 3-7x on ICL frames turning towards new space (paper settings).
    # Nor where the map-free odometry measured the motion the tracker found: walking into new space (the generated
    # two-storey scene: a pillar passed at 1 m, half the points new, the loss 3.1x in one frame, the pose 0.5 cm off)
    # is not a jump, and a camera wrongly lost there makes no keyframe of the new space and is never found again.
    leaves_mapped_space = math.isfinite(e.observed_fraction) and e.observed_fraction < cfg.residual_observed_below
    if e.typical_loss is not None and e.typical_loss > 0 and leaves_mapped_space and not e.odometry_agrees:
        ratio = e.loss / e.typical_loss
        scores["residual"] = (1.0 - ramp(ratio, cfg.residual_high, cfg.residual_low),
                              f"loss {ratio:.1f}x the recent frames'")
    if e.map_disagrees:
        scores["map"] = (DEGRADED_QUALITY, e.map_disagrees)
    if e.unanchored:
        scores["anchor"] = (DEGRADED_QUALITY, e.unanchored)
    if e.lost_before and not e.anchored:
        scores["start"] = (0.0, "no keyframe matches the view, and no pose was tracked yet to start from")
    if e.lost_before and math.isfinite(e.observed_fraction):
        scores["mapped"] = (ramp(e.observed_fraction, cfg.found_observed_low, cfg.found_observed_high),
                            f"{100 * e.observed_fraction:.0f}% of the depth points in mapped space at the tracked "
                            f"pose: not found yet")
    name = min(scores, key=lambda k: scores[k][0])
    value, why = scores[name]
    weak = None if value < cfg.lost_below else weak_view(e.covariance, e.unexplained, cfg)
    if weak:
        value = min(value, DEGRADED_QUALITY)
        if not e.view_constrains:
            why = weak
        elif not e.unanchored:  # (an unanchored pose is not mapped: its own reason says why)
            why = (f"{weak}; the view itself pins the pose down: the map does not hold enough of it yet (mapped, "
                   f"the odometry's motion kept)")
    degraded = bool((weak and not e.view_constrains) or e.unanchored) and not value < cfg.lost_below
    lost = value < cfg.lost_below
    return Quality(value, why if value < cfg.found_above else "ok", lost, degraded)


def weak_view(covariance: Optional[PoseCovariance], unexplained: Optional[np.ndarray], cfg: QualityConfig
              ) -> Optional[str]:
    """Why the view does not determine the pose (the constraint score in the module docstring), None where it
    does: it leaves a direction free and the covariance exceeds the limits, or it constrains a direction only
    weakly and the pose moved along it by more than WEAK_MOVE_M beyond what the constant velocity predicted
    (`unexplained`, world).

    Beyond the velocity, not the whole move: a camera walking 2.5 cm a frame down the synthetic long room (its
    length weakly constrained) was right every frame, and flagging its moves stopped the map from growing."""
    if covariance is None:
        return None
    if covariance.free and (covariance.sigma_m > cfg.degraded_sigma_m or
                            covariance.sigma_deg > cfg.degraded_sigma_deg):
        return degenerate_view(covariance)
    if unexplained is not None and covariance.weakest < WEAK_BELOW:
        along = abs(float(np.dot(unexplained, covariance.weak_direction)))
        if along > WEAK_MOVE_M:
            x, y, z = covariance.weak_direction
            return (f"weakly constrained view: the pose moved {100 * along:.1f} cm beyond the velocity along "
                    f"({x:+.2f}, {y:+.2f}, {z:+.2f}), which the view barely constrains")
    return None


# A change of motion along a weakly constrained direction (information.WEAK_BELOW) beyond this, in one frame, came
# from the odometry's guess rather than the map: 1.4 and 3.1 cm on the generated corridor's turn, where the camera
# crept 0.2 cm a frame throughout.
WEAK_MOVE_M = 0.01


# The quality of a degraded pose: above `lost_below` (it is the best estimate there is, and the next frame's
# prediction) and below `found_above` (a lost camera is not found on a view that cannot place it).
DEGRADED_QUALITY = 0.6


def degenerate_view(covariance: PoseCovariance) -> str:
    x, y, z = covariance.weak_direction
    return (f"degenerate view: the pose is free along ({x:+.2f}, {y:+.2f}, {z:+.2f}) (sigma "
            f"{100 * covariance.sigma_m:.1f} cm, {covariance.sigma_deg:.1f} deg)")


def _observed_note(observed: float) -> str:
    if not math.isfinite(observed):
        return ""
    if observed < 0.5:
        return f" ({100 * observed:.0f}% in mapped space: the view is mostly new or the pose is wrong)"
    return " (the map disagrees with the frame)"


# Well-tracked frames whose median loss is the residual's reference. The loss rises as a camera walks into space
# mapped moments ago (with the mapper behind, on the synthetic long room 0.38 -> 1.27 over 15 frames, every pose
# within 3 mm): against the median of 30 frames that read as a jump (3.3x) and the camera was falsely lost, then
# found again 10-20 cm off. A jump's rise is sudden (3-13x from one frame to the next), and 10 frames still see it.
RESIDUAL_WINDOW = 10


def typical_loss(recent: Sequence[float], minimum: int = 5) -> Optional[float]:
    """The median loss of recent frames that were not lost (the residual score's reference), None until
    `minimum` of them exist. Keep only frames that were tracked well: a reference that followed a runaway would
    follow it away."""
    finite = [x for x in recent if math.isfinite(x)]
    return float(np.median(finite)) if len(finite) >= minimum else None


def is_lost(was_lost: bool, quality: Quality, cfg: Optional[QualityConfig] = None) -> bool:
    """The tracking state after this frame: lost below `lost_below`; once lost, found again only at
    `found_above` (the frame's pose then came from relocalization refined by the tracker)."""
    cfg = cfg or QualityConfig()
    if was_lost:
        return quality.value < cfg.found_above
    return quality.value < cfg.lost_below
