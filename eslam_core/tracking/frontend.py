"""The tracking front end: the pose of each new frame, how far it can be trusted, and whether it becomes a
keyframe.

Prediction: the motion of an external odometry between the last frame and this one when frames carry `odom_pose`,
else the motion measured by frame-to-frame RGB-D odometry from the last well-tracked frame
(`odometry.width`, odometry.py) where it succeeds, else constant velocity (scaled by the time gaps) from
the last well-tracked frames, else the last pose. Tracking refines the prediction against the map (the paper's
rendering tracker or the fast SDF alignment); with `tracking.mode: external` the odometry's pose (expressed in the
map frame by the first frame) is taken as it is. A pose is re-orthonormalised where it is made, and a diverged
optimisation keeps the prediction.

Every tracked frame gets a quality from what the tracker measured (quality.py). Below `quality.lost_below` the
camera is *lost*: the frame makes no keyframe (it is never mapped) and is not the next frame's prediction. While
lost, each frame is first matched against the keyframes (relocalization.py: place recognition, then PnP with the
keyframe's depth); a pose found there is refined by the tracker, and tracking resumes once the quality reaches
`quality.found_above`. Every `mapping.every`-th well-tracked frame is a keyframe.

What the front end needs of the map (`MapView`) is the field, its extent, observed space and the newest keyframe:
the lock-step system gives it the `SceneMap` itself, the tracking process its replica of the mapper's map.
"""
from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import Callable, Optional, Protocol

import numpy as np
import torch

from eslam_core.camera import Intrinsics
from eslam_core.config import Config
from eslam_core.frames import PreparedFrame, rgb_uint8
from eslam_core.geometry import orthonormalize, rotation_angle_deg
from eslam_core.mapping.keyframes import Keyframe
from eslam_core.mapping.map_frame import squared_first_pose
from eslam_core.mapping.observed import ObservedSurfaces
from eslam_core.representation.field import SceneField
from eslam_core.tracking.information import UNCONSTRAINED_BELOW, PoseCovariance, view_information
from eslam_core.tracking.map_check import MapCheck, widened
from eslam_core.tracking.odometry import RGBDOdometry
from eslam_core.tracking.places import KeyframePlaces
from eslam_core.tracking.quality import (RESIDUAL_WINDOW, Quality, TrackingEvidence, is_lost, tracking_quality,
                                         typical_loss, weak_view)
from eslam_core.tracking.relocalization import plausible_jump
from eslam_core.tracking.render_tracker import Tracker, constant_velocity, time_ratio
from eslam_core.tracking.result import TrackingResult
from eslam_core.tracking.sdf_tracker import SDFTracker
from eslam_core.trajectory import TrackedTrajectory

log = logging.getLogger("eslam")

MAX_EXTRAPOLATION = 4.0  # frame gaps the constant-velocity prediction extrapolates over
DEAD_RECKONED_QUALITY = 0.5  # of a pose from the odometry alone (dead_reckon): trusted less than a tracked one
# Degraded frames in a row after which each frame is first matched against the keyframes, as a lost one is: the pose
# may have slid along the free direction, and a tracker back on a constrained view from a pose tens of centimetres
# off can settle there with every point on the map (the generated corridor, 36 cm off).
RECHECK_AFTER = 5
# Frames an unanchored pose (quality.py: after such a run, not yet placed by the keyframes) waits for them before
# tracking goes on from it as it is: a camera that walked on into new space is never placed, and must map again.
# The map check (map_check.py) still says so later if that pose was off.
ANCHOR_WAIT = 90
# Relocalizations that confirm the predicted motion before an unanchored pose is anchored again. One is not enough:
# on the generated corridor's turn back (3 degrees a frame) the odometry moved the two frames after a confirmed one
# 10 cm off, and the tracker settled there, every direction constrained; while unanchored, each frame starts from
# its relocalization where there is one.
ANCHOR_CONFIRMATIONS = 3
AGREE_M, AGREE_DEG = 0.03, 3.0  # two poses of a frame this close are the same start for a tracker


# A view with less of its depth in mapped space than this has left the map: against a map that lags the keyframes,
# the frame waits for the newer map (TrackingFrontEnd.track's `catch_up`).
MAPPED_AT_LEAST = 0.5


def make_tracker(cfg: Config, dirs_cam: torch.Tensor, intr: Intrinsics):
    """The tracker the config asks for: the paper's rendering tracker or the fast SDF alignment."""
    if cfg.tracking.method == "sdf":
        return SDFTracker.of(cfg, dirs_cam, intr)
    return Tracker.of(cfg, dirs_cam, intr.height, intr.width)


def agrees(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two poses of a frame are the same within a tracker's basin (AGREE_M, AGREE_DEG)."""
    d = np.linalg.inv(a) @ b
    return float(np.linalg.norm(d[:3, 3])) < AGREE_M and rotation_angle_deg(d[:3, :3]) < AGREE_DEG


def left_the_map(result: TrackingResult) -> bool:
    """Whether the tracker found too little of the frame in mapped space to place it."""
    return not math.isfinite(result.loss) or (math.isfinite(result.mapped_fraction)
                                              and result.mapped_fraction < MAPPED_AT_LEAST)


class MapView(Protocol):
    field: Optional[SceneField]
    version: int  # changes whenever the field's values change
    extent: Optional[np.ndarray]
    observed: Optional[ObservedSurfaces]
    # The world pose of the map's frame (a submap's anchor, submaps/atlas.py); the field, its extent, observed
    # space and the keyframes are in that frame. None: the world's own.
    anchor: Optional[np.ndarray]

    def newest_keyframe(self) -> Optional[Keyframe]: ...


@dataclass
class TrackedPose:
    pose: torch.Tensor  # (4, 4) float32 camera-to-world
    prediction: torch.Tensor
    loss: float
    keyframe: bool
    quality: Quality
    lost: bool  # the camera is lost after this frame (its pose is not to be trusted, nor mapped)
    relocalized_from: Optional[int] = None  # the keyframe whose match gave this frame's starting pose
    covariance: Optional[PoseCovariance] = None  # of the pose (information.py); None where nothing measured it

    @property
    def covariance_matrix(self) -> Optional[np.ndarray]:
        return None if self.covariance is None else self.covariance.matrix


class TrackingFrontEnd:
    def __init__(self, cfg: Config, intr: Intrinsics, dirs_cam: torch.Tensor, closes_loops: bool = True):
        """`closes_loops`: the caller takes the map checks as loop closure's candidates (with submaps); the
        pipelined runtime's tracker does not (its mapper closes the loops)."""
        self.cfg, self.intr, self.dirs_cam = cfg, intr, dirs_cam
        self.tracker = make_tracker(cfg, dirs_cam, intr) if cfg.tracking.mode == "track" else None
        self.map_from_odom: Optional[np.ndarray] = None  # fixed by the first frame that carries odometry
        self.last_odom: Optional[np.ndarray] = None
        self.lost = False
        self.good: list[int] = []  # trajectory positions of the last well-tracked frames (the prediction's)
        self.recent_losses: deque = deque(maxlen=RESIDUAL_WINDOW)  # well-tracked frames' (the residual's)
        self.since_keyframe = 0
        self.degraded_run = 0  # frames in a row whose view did not determine the pose (quality.weak_view)
        self.unanchored: Optional[PoseCovariance] = None  # after a long such run: its last frame's covariance
        self.unanchored_for = 0  # frames since the run ended
        self.confirmations = 0  # relocalizations since then that confirmed the predicted motion
        self.odometry_predicted = False  # the newest prediction is the frame-to-frame odometry's motion
        # The last frame's own view pinned its pose down where the map did not yet (quality.py: the map lacks the
        # view): the odometry, which registers the frames, saw what the map lacks, and its motion is kept.
        self.map_lacks_view = False
        self.fallback_pose = np.eye(4)
        self.odometry = None  # frame-to-frame odometry, its reference the last well-tracked frame
        if cfg.odometry.width > 0 and self.tracker is not None:
            self.odometry = RGBDOdometry(intr, cfg.odometry.width, cfg.camera.max_depth, cfg.odometry.iterations)
        # The keyframes for relocalization and the map's check against itself (places.py), when enabled.
        self.places: Optional[KeyframePlaces] = None
        if cfg.relocalization.enabled and self.tracker is not None:
            self.places = KeyframePlaces(cfg.relocalization, intr, cfg.run.seed,
                                         keep_checks=closes_loops and cfg.submaps.radius_m > 0
                                         and cfg.submaps.loop_closure)

    def start_lost(self, keyframes) -> None:
        """A loaded map: the camera is not where the map ended, it has to be found against the map's keyframes."""
        self.lost, self.good = True, []
        if self.places is not None:
            self.places.start_lost(keyframes)
        if len(keyframes):  # the prior of a first frame that no keyframe explains: where the map ended
            self.fallback_pose = keyframes[-1].pose.double().numpy()

    def remember(self, kf: Keyframe) -> None:
        """A new keyframe, for relocalization (KeyframePlaces.remember: indexed later)."""
        if self.places is not None:
            self.places.remember(kf)

    def index_next(self) -> bool:
        """One unit of the idle work (KeyframePlaces.index_next); False if nothing waits."""
        return self.places is not None and self.places.index_next()

    @property
    def idle_work(self) -> bool:
        return self.places is not None and self.places.idle_work

    @property
    def map_check(self) -> Optional[MapCheck]:
        """The newest keyframe placed by older ones (map_check.py), None before one was."""
        return None if self.places is None else self.places.check

    @property
    def map_disagrees(self) -> Optional[MapCheck]:
        """The newest map check, where it found the map disagreeing with itself (else None)."""
        return None if self.places is None else self.places.disagreement

    def forget(self, numbers) -> None:
        if self.places is not None:
            self.places.forget(numbers)

    def refine(self, poses: dict) -> None:
        if self.places is not None:
            self.places.refine(poses)

    def first_pose(self, pf: PreparedFrame, trajectory: TrackedTrajectory) -> np.ndarray:
        """The first frame fixes the map frame: its ground-truth pose when known (outputs share its frame), else the
        first camera's squared with the scene's surfaces (`scene.align_axes`, unless a bound in that frame is set)."""
        if pf.gt_pose is not None:
            pose0 = pf.gt_pose
        elif self.cfg.scene.align_axes and self.cfg.scene.bound is None:
            pose0 = squared_first_pose(pf.depth.cpu().numpy(), self.intr)
        else:
            pose0 = np.eye(4)
        self._note_odometry(pf, pose0)
        self.good = [len(trajectory)]
        if self.odometry is not None:
            self.odometry.set_reference(len(trajectory), self.odometry.frame(pf.rgb, pf.depth))
        return orthonormalize(pose0)

    def _note_odometry(self, pf: PreparedFrame, pose: np.ndarray) -> None:
        if pf.odom_pose is None:
            return
        if self.map_from_odom is None:
            self.map_from_odom = pose @ np.linalg.inv(pf.odom_pose)
        self.last_odom = pf.odom_pose

    def predict(self, pf: PreparedFrame, trajectory: TrackedTrajectory, odometry_frame=None
                ) -> tuple[np.ndarray, float, Optional[np.ndarray]]:
        """The predicted pose (from the last well-tracked frames only), the time since the last of them in
        units of the usual frame gap, and the pose to keep along the directions the frame does not constrain
        where that is not the prediction (else None). `odometry_frame`: this frame prepared for the frame-to-frame
        odometry.

        The odometry sees what the tracker sees: where the view leaves a direction free (a wall, a corridor) its
        motion along it is a guess too, and on the synthetic degenerate views it returned motions 3-25 cm off
        along it, frame after frame, while the camera crept 0.2 cm. A constant velocity is no better there: one
        such motion becomes the velocity. Along what the frame does not constrain the tracker keeps the last pose
        (information.py), and after a degraded frame the prediction keeps the camera where it was (`_held`): the
        error grows no faster than the camera moves, and the frame says it is degraded. External odometry does
        not see the view: its pose is kept as it is."""
        self.odometry_predicted = False
        if len(trajectory) == 0:
            return self.fallback_pose, 1.0, None
        last = self.good[-1] if self.good else len(trajectory) - 1
        prev = trajectory.pose(last)
        gap = 1.0
        if len(self.good) >= 2:
            a, b = trajectory.records[self.good[-2]].timestamp, trajectory.records[last].timestamp
            gap = time_ratio(a, b, pf.timestamp, limit=1e9)
        if pf.odom_pose is not None and self.last_odom is not None:
            if self.cfg.tracking.mode == "external":
                return self.map_from_odom @ pf.odom_pose, gap, None
            return prev @ np.linalg.inv(self.last_odom) @ pf.odom_pose, gap, None
        if odometry_frame is not None and self.odometry.reference_key == last:
            motion = self.odometry.motion(odometry_frame)
            if motion is not None:
                self.odometry_predicted = not self.degraded_run
                return self._held(prev @ motion, prev), gap, \
                    None if self.degraded_run or self.map_lacks_view else prev
        if not self.good:
            return prev, gap, None
        return self._held(self._velocity_prediction(trajectory, gap), prev), gap, None

    def _velocity_prediction(self, trajectory: TrackedTrajectory, gap: float) -> np.ndarray:
        """The constant-velocity pose from the last well-tracked frames (at least one), `gap` frame gaps on.

        After a long pause (over MAX_EXTRAPOLATION frame gaps) the velocity says nothing: predict no motion. A
        camera lost for a few frames keeps the velocity of its last tracked ones: they are the frames before the
        loss, and a camera that walked on while lost (2.5 cm a frame on the synthetic long room) was otherwise
        refined from where it was last tracked, 10 cm behind, and on a wall that lets the pose slide, found there."""
        prev = trajectory.pose(self.good[-1])
        if len(self.good) < 2 or not self.cfg.tracking.constant_velocity or gap > MAX_EXTRAPOLATION:
            return prev
        return constant_velocity(trajectory.pose(self.good[-2]), prev, gap)

    def _held(self, predicted: np.ndarray, prev: np.ndarray) -> np.ndarray:
        """After a degraded frame, the predicted turn with the camera where it was: on a view that left the pose
        free the odometry's moves were off by 3-25 cm frame after frame, and a velocity made of one of them ran
        the generated corridor's pose off by 9 cm a frame; its turns stay right (walls and floor fix them), and
        without them the corridor's pan left the pose 12 degrees behind."""
        if not self.degraded_run:
            return predicted
        held = predicted.copy()
        held[:3, 3] = prev[:3, 3]
        return held

    def track(self, pf: PreparedFrame, view: MapView, trajectory: TrackedTrajectory,
              catch_up: Optional[Callable[[], bool]] = None) -> TrackedPose:
        """The frame's pose against `view`. `catch_up`: for a map that lags the keyframes (the pipelined runtime,
        offline), brings the view up to every keyframe made so far and says whether it changed; it is called when
        the view has left the mapped space, and the frame is then tracked again on the newer map."""
        odometry_frame = self.odometry.frame(pf.rgb, pf.depth) if self.odometry is not None else None
        predicted, gap, model = self.predict(pf, trajectory, odometry_frame)
        init = torch.from_numpy(orthonormalize(predicted)).float()
        free_prior = None if model is None else torch.from_numpy(orthonormalize(model)).float()
        if self.tracker is None:  # external mode: the odometry's pose, mapping only
            self._note_odometry(pf, init.double().numpy())
            return self._decided(len(trajectory), init, init, 0.0, Quality(1.0, "ok", False), None)
        found = None
        recheck = self.lost or self.degraded_run >= RECHECK_AFTER or self.unanchored is not None
        if recheck and self.places is not None:
            found = self.places.relocalize(rgb_uint8(pf.rgb).numpy(), pf.depth.numpy())
            if found is not None and not self.lost and not plausible_jump(found.pose, predicted,
                                                                        self.cfg.relocalization.max_jump_m):
                log.info("frame %d: relocalized %.1f m from its predicted position, beyond relocalization.max_jump_m "
                         "for a camera that is not lost: another place that looks alike, not used", pf.index,
                         float(np.linalg.norm(found.pose[:3, 3] - predicted[:3, 3])))
                found = None
            if found is not None:
                init, free_prior = torch.from_numpy(orthonormalize(found.pose)).float(), None
        result = self._track_against(view, pf, init, free_prior)
        if catch_up is not None and left_the_map(result) and catch_up():
            result = self._track_against(view, pf, init, free_prior)
        pose = result.pose
        if not torch.isfinite(pose).all():  # a diverged optimisation must not poison the trajectory and the map
            log.warning("frame %d: tracking diverged (non-finite pose); keeping the motion model's prediction",
                        pf.index)
            pose = init
        pose = orthonormalize(pose)
        disagrees = self.map_disagrees
        unexplained = None  # the pose's move beyond the constant velocity's (quality.py, weak_view)
        if self.good and found is None:
            unexplained = pose[:3, 3].double().numpy() - self._velocity_prediction(trajectory, gap)[:3, 3]
        weak = weak_view(result.covariance, unexplained, self.cfg.quality) is not None
        # (Only where the map leaves the pose free: the view's own information costs a millisecond.)
        self.map_lacks_view = weak and view_information(pf.depth.cpu().numpy(), self.intr) >= UNCONSTRAINED_BELOW
        weak = weak and not self.map_lacks_view
        confirmed = found is not None and agrees(found.pose, predicted)
        # The map-free odometry's motion from a well-tracked frame, and the map's pose agreeing with it: no jump.
        odometry_agrees = self.odometry_predicted and found is None and agrees(pose.double().numpy(), predicted)
        unanchored = None if weak else self._anchoring(pf.index, confirmed)
        evidence = TrackingEvidence(result.depth_fraction, result.inlier_fraction, result.observed_fraction,
                                    result.loss, (torch.linalg.inv(init.double()) @ pose.double()).numpy(),
                                    typical_loss(self.recent_losses), 1.0 if found is not None else gap, self.lost,
                                    found is not None or self._prior_holds(pf), result.covariance,
                                    None if disagrees is None else disagrees.reason, unanchored, unexplained,
                                    odometry_agrees, self.map_lacks_view)
        quality = tracking_quality(evidence, self.cfg.quality)
        tracked = self._decided(len(trajectory), pose, init, result.loss, quality,
                                None if found is None else found.keyframe_id, pf, odometry_frame)
        self.degraded_run = self.degraded_run + 1 if weak and quality.degraded else 0
        if self.degraded_run >= RECHECK_AFTER:
            self.unanchored, self.unanchored_for, self.confirmations = result.covariance, 0, 0
        covariance = result.covariance
        if unanchored and covariance is not None:  # at least as uncertain as where the run left it
            covariance = PoseCovariance(covariance.matrix + self.unanchored.matrix, covariance.free)
        tracked.covariance = covariance if disagrees is None else widened(covariance, disagrees)
        return tracked

    def _track_against(self, view: MapView, pf: PreparedFrame, init: torch.Tensor,
                       free_prior: Optional[torch.Tensor]) -> TrackingResult:
        """The tracker's answer from `init` against the view, in the world frame (a submap is tracked in its own
        frame). (The extent test uses the starting pose: a few centimetres off at most, and it saves a pass.)"""
        if view.anchor is None:
            return self.tracker.track(view.field, pf, init, view.extent, view.observed, view.newest_keyframe(),
                                      view.version, free_prior)
        to_local = torch.from_numpy(np.linalg.inv(view.anchor)).to(init.dtype)
        result = self.tracker.track(view.field, pf, to_local @ init, view.extent, view.observed,
                                    view.newest_keyframe(), view.version,
                                    None if free_prior is None else to_local @ free_prior)
        return result.in_world(view.anchor)

    def _anchoring(self, index: int, confirmed: bool) -> Optional[str]:
        """For a frame whose view constrains the pose: why its pose may still be off along a direction that a run
        of earlier views left free (quality.py: unanchored), None where it is not. A run of RECHECK_AFTER such
        frames unanchors the pose (track); ANCHOR_CONFIRMATIONS relocalizations that confirm the motion predicted
        from the frame before (`confirmed`), or ANCHOR_WAIT frames, anchor it again; so does a view that the map
        lacks (the camera walked on into space that no keyframe holds: none can place it, and without mapping the
        view leaves the map; the generated two-storey walk, past a pillar that filled the view for 20 frames, into
        the room beyond, was lost there)."""
        if self.unanchored is None:
            return None
        self.confirmations += confirmed
        if self.confirmations >= ANCHOR_CONFIRMATIONS:
            log.info("frame %d: placed by the keyframes again after a view that left the pose free", index)
            self.unanchored = None
            return None
        if self.map_lacks_view:
            log.warning("frame %d: not placed by the keyframes after a view that left the pose free, and the map "
                        "lacks this view; tracking and mapping go on from this pose", index)
            self.unanchored = None
            return None
        self.unanchored_for += 1
        if self.unanchored_for > ANCHOR_WAIT:
            log.warning("frame %d: not placed by the keyframes in %d frames after a view that left the pose free; "
                        "tracking and mapping go on from this pose", index, ANCHOR_WAIT)
            self.unanchored = None
            return None
        x, y, z = self.unanchored.weak_direction
        return (f"not placed by the keyframes yet since a view left the pose free along ({x:+.2f}, {y:+.2f}, "
                f"{z:+.2f}) ({self.unanchored_for} frames)")

    def dead_reckon(self, pf: PreparedFrame, trajectory: TrackedTrajectory) -> Optional[TrackedPose]:
        """A frame that came before there is a map to track against (a live camera streams from its first frame
        while the map of that frame warms up): its pose from the frame-to-frame odometry alone. The odometry's
        reference moves on to it, so that the first frame tracked against the map starts from the motion since
        the last such frame, not from the whole warm-up's (ICL at 30 Hz: 1.6 s, too far for the odometry and the
        SDF's basin). Never a keyframe: only tracked poses are mapped. None without odometry or where it failed."""
        if self.odometry is None or self.lost or not self.good or self.odometry.reference_key != self.good[-1]:
            return None
        odometry_frame = self.odometry.frame(pf.rgb, pf.depth)
        motion = self.odometry.motion(odometry_frame)
        if motion is None:
            return None
        position = len(trajectory)
        pose = torch.from_numpy(orthonormalize(trajectory.pose(self.good[-1]) @ motion)).float()
        self.good = (self.good + [position])[-2:]
        self.odometry.set_reference(position, odometry_frame)
        self._note_odometry(pf, pose.double().numpy())
        return TrackedPose(pose, pose, float("nan"), False, Quality(DEAD_RECKONED_QUALITY, "odometry only: no map yet",
                                                                   False), False)

    def _prior_holds(self, pf: PreparedFrame) -> bool:
        """Whether the prediction of a lost camera is worth refining without a relocalization match: without a
        relocalizer it is all there is; with odometry it is the odometry's; else the last tracked pose, which a
        loaded map does not have (where the map ended says nothing about where the camera is). A camera lost while
        mapping, e.g. ahead of a map that has not grown yet, is found again from where it was last tracked."""
        if self.places is None or (pf.odom_pose is not None and self.last_odom is not None):
            return True
        return bool(self.good)

    def _decided(self, position: int, pose: torch.Tensor, init: torch.Tensor, loss: float, quality: Quality,
                 relocalized_from: Optional[int], pf: Optional[PreparedFrame] = None,
                 odometry_frame=None) -> TrackedPose:
        """The tracking state after this frame, and whether it is a keyframe."""
        was_lost = self.lost
        self.lost = is_lost(was_lost, quality, self.cfg.quality) and self.cfg.quality.enabled
        if self.lost and not was_lost:
            log.warning("frame %d: tracking lost (%s); its pose is not used, relocalizing against the keyframes",
                        pf.index if pf else position, quality.reason)
        elif was_lost and not self.lost:
            log.info("frame %d: tracking resumed%s (quality %.2f)", pf.index if pf else position,
                     f", relocalized against keyframe {relocalized_from}" if relocalized_from is not None else "",
                     quality.value)
        keyframe = False
        if not self.lost:
            # (The move from the last tracked pose to a relocalized one is a correction, not a velocity.)
            self.good = [position] if relocalized_from is not None else (self.good + [position])[-2:]
            if math.isfinite(loss):
                self.recent_losses.append(loss)
            if pf is not None:
                self._note_odometry(pf, pose.double().numpy())
            if odometry_frame is not None:
                self.odometry.set_reference(position, odometry_frame)
            self.since_keyframe += 1
            # A degraded pose may have slid along the free direction: mapping it would put the slide into the map.
            keyframe = self.since_keyframe >= self.cfg.mapping.every and self.cfg.run.mode == "slam" and \
                not quality.degraded
            if keyframe:
                self.since_keyframe = 0
        return TrackedPose(pose, init, loss, keyframe, quality, self.lost, relocalized_from)

