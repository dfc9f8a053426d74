"""Tracking quality: tracked frames are trusted, covered lenses, jumps and runaway corrections are lost, with a
reason. The evidence figures are those measured on the synthetic room (SDF tracker against a map fitted to three
keyframes, frames 13-29 tracked from the constant-velocity prediction, then from poses 10-50 cm / 5-20 degrees
off; see tracking/quality.py)."""
from __future__ import annotations

import math
from dataclasses import replace
from collections import deque

import numpy as np
import pytest

from eslam_core.config import ConfigError
from eslam_core.geometry import rotvec_to_matrix
from eslam_core.tracking.quality import (RESIDUAL_WINDOW, QualityConfig, TrackingEvidence, is_lost, tracking_quality,
                                         typical_loss)


def motion(metres: float, degrees: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rotvec_to_matrix(np.radians(degrees) * np.array([0.0, 0.6, 0.8]))
    m[:3, 3] = [metres, 0.0, 0.0]
    return m


def evidence(depth=0.9, inliers=0.99, observed=1.0, loss=0.44, typical=0.44, corr=(0.001, 0.1), gap=1.0):
    return TrackingEvidence(depth, inliers, observed, loss, motion(*corr), typical, gap)


def test_tracked_frames_are_trusted():
    for inliers, loss in ((0.98, 0.429), (1.0, 0.454), (0.97, 0.480)):
        q = tracking_quality(evidence(inliers=inliers, loss=loss))
        assert q.value == 1.0 and q.reason == "ok" and not q.lost
    # the tracker may correct a poor prediction by 10 cm / 5 degrees and be right: still trusted
    assert tracking_quality(evidence(loss=0.497, corr=(0.101, 5.0))).value == 1.0


@pytest.mark.parametrize("inliers,observed,loss,corr", [
    (0.34, 0.37, 2.951, (0.209, 7.4)),  # camera jumped 20 cm / 10 deg
    (0.17, 0.19, 5.633, (0.053, 1.6)),  # 30 cm / 15 deg
    (0.31, 0.45, 4.661, (0.328, 9.2)),  # 50 cm / 20 deg
    (0.11, 0.15, 5.181, (0.036, 1.0)),  # 30 cm
    (0.22, 0.25, 5.661, (0.049, 1.4)),  # 20 deg
])
def test_jumps_of_the_camera_are_lost(inliers, observed, loss, corr):
    q = tracking_quality(evidence(inliers=inliers, observed=observed, loss=loss, corr=corr))
    assert q.lost and q.value < 0.5
    assert q.reason != "ok"
    # without a loss reference yet (the first frames), the inliers alone still say so
    assert tracking_quality(evidence(inliers=inliers, observed=observed, loss=loss, typical=None, corr=corr)).lost


def test_each_piece_of_evidence_names_itself():
    covered = tracking_quality(evidence(depth=0.0, inliers=0.0, observed=math.nan, loss=math.nan))
    assert covered.lost and covered.value == 0.0 and "0% of the pixels have depth" in covered.reason
    few_depth = tracking_quality(evidence(depth=0.03))
    assert few_depth.lost and "pixels have depth" in few_depth.reason
    off_map = tracking_quality(evidence(inliers=0.15, observed=0.2))
    assert off_map.lost and "lie on the map" in off_map.reason and "mostly new" in off_map.reason
    disagrees = tracking_quality(evidence(inliers=0.15, observed=0.9))
    assert "map disagrees" in disagrees.reason
    assert not tracking_quality(evidence(loss=2.2)).lost  # 5x the typical loss, the points where the map is
    residual = tracking_quality(evidence(loss=2.2, observed=0.5))  # 5x, and half the points off the mapped space
    assert residual.lost and "5.0x" in residual.reason
    runaway = tracking_quality(evidence(corr=(0.5, 3.0)))  # the 50 cm jump in one frame
    assert runaway.lost and "50 cm" in runaway.reason


def test_motion_limits_grow_with_the_time_since_the_last_frame():
    assert tracking_quality(evidence(corr=(0.4, 2.0))).lost
    assert not tracking_quality(evidence(corr=(0.4, 2.0), gap=4.0)).lost  # three frames were dropped


def test_quality_falls_steadily_with_the_inliers():
    values = [tracking_quality(evidence(inliers=f)).value for f in np.linspace(1.0, 0.0, 11)]
    assert all(a >= b for a, b in zip(values, values[1:])) and values[0] == 1.0 and values[-1] == 0.0


def test_unmeasured_fractions_give_no_score():
    q = tracking_quality(evidence(depth=math.nan, inliers=math.nan, observed=math.nan))
    assert q.value == 1.0 and not q.lost
    # The rendering tracker measures no observed space: its loss, rising as the camera turns to new space (ICL,
    # paper settings: 6.6x the recent frames'), is no evidence of a jump.
    assert not tracking_quality(evidence(inliers=0.9, observed=math.nan, loss=6.6, typical=1.0)).lost
    assert tracking_quality(evidence(inliers=0.9, observed=0.42, loss=6.6, typical=1.0)).lost


def test_lost_state_has_hysteresis():
    marginal = tracking_quality(evidence(inliers=0.45))  # quality 0.625: between lost_below and found_above
    assert 0.5 < marginal.value < 0.7 and not marginal.lost
    assert not is_lost(False, marginal)  # a tracking camera is not lost by it...
    assert is_lost(True, marginal)  # ...and a lost one is not found by it
    assert not is_lost(True, tracking_quality(evidence()))
    assert is_lost(False, tracking_quality(evidence(inliers=0.1)))


def test_a_lost_camera_is_found_only_where_the_map_is():
    """7-Scenes localization restart: the tracker settled where 95 % of the 25 % of points in observed space fit
    (80 cm off). A tracked camera looking at that much new space is fine."""
    guess = TrackingEvidence(0.94, 0.95, 0.25, 5.39, motion(0.001, 0.1), None, 1.0, lost_before=True)
    q = tracking_quality(guess)
    assert is_lost(True, q) and "25% of the depth points in mapped space" in q.reason  # stays lost
    assert not tracking_quality(TrackingEvidence(0.94, 0.95, 0.25, 5.39, motion(0.001, 0.1), None, 1.0)).lost
    found = tracking_quality(TrackingEvidence(0.94, 0.95, 0.8, 5.39, motion(0.001, 0.1), None, 1.0, lost_before=True))
    assert found.value == 1.0 and not is_lost(True, found)
    # Tracked from a guess (no relocalization match, no recent pose): however well it fits, not found.
    guessed = tracking_quality(TrackingEvidence(0.94, 0.95, 0.8, 5.39, motion(0.001, 0.1), None, 1.0,
                                                lost_before=True, anchored=False))
    assert guessed.lost and "no keyframe matches" in guessed.reason


def test_typical_loss_waits_for_enough_frames():
    assert typical_loss([0.4, 0.5]) is None
    assert typical_loss([0.4, 0.5, float("nan"), 0.45, 0.42, 0.9]) == pytest.approx(0.45)


# Frames 14-33 of the synthetic long room through the pipelined runtime, the mapper behind the tracker: loss and
# fraction of the points in observed space; every pose within 3 mm of the truth.
WALK_INTO_NEW_SPACE = [(0.388, 0.95), (0.454, 0.92), (0.408, 0.90), (0.369, 0.88), (0.378, 0.85), (0.467, 0.87),
                       (0.434, 0.85), (0.450, 0.84), (0.488, 0.83), (0.467, 0.81), (0.457, 0.78), (0.484, 0.74),
                       (0.469, 0.75), (0.755, 0.71), (0.783, 0.67), (0.932, 0.65), (0.769, 0.61), (0.732, 0.58),
                       (1.116, 0.65), (1.273, 0.62)]


def test_a_loss_that_rises_as_the_camera_walks_into_new_space_is_not_a_jump():
    recent = deque([0.334, 0.378, 0.364, 0.330, 0.372, 0.377, 0.339, 0.359, 0.395, 0.390, 0.338, 0.378, 0.368],
                   maxlen=RESIDUAL_WINDOW)
    for loss, observed in WALK_INTO_NEW_SPACE:
        q = tracking_quality(evidence(inliers=0.98, observed=observed, loss=loss, typical=typical_loss(recent)))
        assert not q.lost, q.reason
        recent.append(loss)
    # the same loss straight after well-tracked frames is a jump's
    jump = tracking_quality(evidence(inliers=0.98, observed=0.62, loss=1.273, typical=0.37))
    assert jump.lost and "3.4x" in jump.reason


def test_a_sudden_loss_in_new_space_is_not_a_jump_where_the_odometry_measured_the_same_motion():
    # The generated two-storey walk passing a pillar at 1 m: half the points new, the loss 3.1x the recent frames'
    # in one frame, the tracked pose 0.5 cm from the odometry's (and 0.5 cm from the truth).
    passing = evidence(inliers=1.0, observed=0.52, loss=0.242, typical=0.0773, corr=(0.005, 0.2))
    assert tracking_quality(passing).lost  # the loss alone reads as a jump's ...
    q = tracking_quality(replace(passing, odometry_agrees=True))  # ... the frame-to-frame motion says it is not
    assert not q.lost and q.value == 1.0


def test_config_is_validated():
    def check(ok, key, message):
        if not ok:
            raise ConfigError(f"invalid value for '{key}': {message}")

    QualityConfig().validate(check)
    with pytest.raises(ConfigError, match="quality.lost_below"):
        QualityConfig(lost_below=0.8, found_above=0.7).validate(check)
    with pytest.raises(ConfigError, match="quality.inliers_low"):
        QualityConfig(inliers_low=0.7, inliers_high=0.6).validate(check)


def test_a_pose_is_degraded_where_the_view_leaves_a_direction_free_not_where_it_is_noisy():
    """Degraded means "free along a direction" (information.py): a covariance as wide but constrained in every
    direction (real depth noise: the rendering tracker's on 7-Scenes, 2 cm) is published, not degraded."""
    from dataclasses import replace

    from eslam_core.tracking.information import PoseCovariance

    wide = np.diag([0.03**2] * 3 + [1e-6] * 3)
    noisy = tracking_quality(replace(evidence(), covariance=PoseCovariance(wide)))
    assert noisy.value == 1.0 and not noisy.degraded
    free = tracking_quality(replace(evidence(), covariance=PoseCovariance(wide, free=True)))
    assert free.degraded and free.value < QualityConfig().found_above and free.reason.startswith("degenerate view")
    narrow = tracking_quality(replace(evidence(), covariance=PoseCovariance(np.diag([1e-6] * 6), free=True)))
    assert not narrow.degraded  # a free direction the prior keeps tight (a still camera) is no concern


def test_a_view_that_pins_the_pose_down_where_the_map_does_not_is_capped_but_mapped():
    """The map lacks the view (a room walked into, not settled yet): the pose is as free against the map, and says
    so, but the frame is not degraded, so that it is mapped and the map learns the view."""
    from dataclasses import replace

    from eslam_core.tracking.information import PoseCovariance

    free = PoseCovariance(np.diag([0.03**2] * 3 + [1e-6] * 3), free=True)
    q = tracking_quality(replace(evidence(), covariance=free, view_constrains=True))
    assert not q.degraded and not q.lost and q.value < QualityConfig().found_above
    assert q.reason.startswith("degenerate view") and "the map does not hold enough of it yet" in q.reason
    assert tracking_quality(replace(evidence(), covariance=free)).degraded  # the view itself leaves it free
    why = "not placed by the keyframes yet since a view left the pose free along (+1.00, +0.00, +0.00) (3 frames)"
    unanchored = tracking_quality(replace(evidence(), covariance=free, view_constrains=True, unanchored=why))
    assert unanchored.degraded and unanchored.reason == why  # not mapped, and not said to be


def test_a_map_that_disagrees_with_itself_caps_the_quality_without_degrading_the_view():
    from dataclasses import replace

    q = tracking_quality(replace(evidence(), map_disagrees="the map disagrees with itself: ..."))
    assert q.value < QualityConfig().found_above and not q.lost and not q.degraded
    assert q.reason.startswith("the map disagrees with itself")


def test_an_unanchored_pose_is_degraded_on_a_constrained_view_until_placed_again():
    """After a run of views that left the pose free, a constrained view's pose may still carry the slide: it is
    degraded (not mapped) with the reason, though its own covariance is tight; a lost frame stays lost."""
    from dataclasses import replace

    from eslam_core.tracking.information import PoseCovariance

    tight = PoseCovariance(np.diag([1e-6] * 6))
    why = "not placed by the keyframes yet since a view left the pose free along (+1.00, +0.00, +0.00) (3 frames)"
    q = tracking_quality(replace(evidence(), covariance=tight, unanchored=why))
    assert q.degraded and not q.lost and q.value < QualityConfig().found_above and q.reason == why
    assert not tracking_quality(replace(evidence(), covariance=tight)).degraded
    lost = tracking_quality(replace(evidence(), inlier_fraction=0.05, unanchored=why))
    assert lost.lost and not lost.degraded


def test_a_move_along_a_weakly_constrained_direction_is_degraded():
    """A direction the view constrains only weakly (information.WEAK_BELOW) lets the odometry's guess through: a pose
    that moved along it by over WEAK_MOVE_M beyond the constant velocity is degraded; the same move along a direction that is
    well constrained, or a small one along the weak one, is not."""
    from dataclasses import replace

    from eslam_core.tracking.information import WEAK_BELOW, PoseCovariance
    from eslam_core.tracking.quality import WEAK_MOVE_M

    along_x = np.diag([0.015**2, 0.002**2, 0.002**2] + [1e-6] * 3)  # the weakest axis is x
    weak, strong = PoseCovariance(along_x, weakest=0.5 * WEAK_BELOW), PoseCovariance(along_x, weakest=2 * WEAK_BELOW)
    big, small = np.array([3 * WEAK_MOVE_M, 0, 0]), np.array([0.5 * WEAK_MOVE_M, 0, 0])
    q = tracking_quality(replace(evidence(), covariance=weak, unexplained=big))
    assert q.degraded and q.reason.startswith("weakly constrained view") and q.value < QualityConfig().found_above
    assert not tracking_quality(replace(evidence(), covariance=weak, unexplained=small)).degraded
    assert not tracking_quality(replace(evidence(), covariance=strong, unexplained=big)).degraded
    assert not tracking_quality(replace(evidence(), covariance=weak, unexplained=np.array([0, 3 * WEAK_MOVE_M, 0]))).degraded
