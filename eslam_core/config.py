"""Typed, validated configuration.

A configuration is a YAML file whose sections mirror the dataclasses below. A preset may `extends:` another file
(path relative to itself, or the name of a shipped preset such as `replica`). Loading checks every key: an unknown
key, a wrong type or an impossible value stops with a `ConfigError` naming the key and the file.
"""
from __future__ import annotations

import copy
import dataclasses
import types
import typing
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Optional

import yaml

from eslam_core.atomic import write_atomic  # written whole or not at all, like every output


class ConfigError(ValueError):
    """A configuration file is invalid; the message names the key, the file and what to do."""


@dataclass
class CameraConfig:
    """Overrides of what the data set reader finds (all optional)."""

    width: Optional[int] = None
    height: Optional[int] = None
    fx: Optional[float] = None
    fy: Optional[float] = None
    cx: Optional[float] = None
    cy: Optional[float] = None
    depth_scale: Optional[float] = None  # raw depth units per metre
    image_scale: float = 1.0  # resize input images by this factor before SLAM (speed / resolution trade-off)
    max_depth: float = 0.0  # ignore depth beyond this many metres (0 = keep all)

    def validate(self, check) -> None:
        intr = [self.width, self.height, self.fx, self.fy, self.cx, self.cy]
        check(all(v is None for v in intr) or all(v is not None for v in intr),
              "camera", "give all of width, height, fx, fy, cx, cy, or none of them")
        check(0.0 < self.image_scale <= 1.0, "camera.image_scale", "must be in (0, 1]")
        check(self.max_depth >= 0.0, "camera.max_depth", "must be >= 0 (0 disables the cut)")
        check(self.depth_scale is None or self.depth_scale > 0, "camera.depth_scale", "must be positive")


@dataclass
class DatasetConfig:
    kind: str = "auto"  # auto | tum | icl | replica | scannet | 7scenes
    # Resample colour that is not registered to depth (7-Scenes) onto the depth camera's pixels as it is read.
    register_colour: bool = True

    def validate(self, check) -> None:
        kinds = ("auto", "tum", "icl", "replica", "scannet", "7scenes")
        check(self.kind in kinds, "dataset.kind", f"must be one of {', '.join(kinds)}")


@dataclass
class SceneConfig:
    # [[xmin, ymin, zmin], [xmax, ymax, zmax]] in the world frame (metres): a hard limit, the map covers exactly
    # this box. None: the map starts around the first frame and grows by whole coarse cells wherever a keyframe's
    # depth falls outside it (mapping/extent.py), up to `max_extent` metres per axis.
    bound: Optional[list] = None
    bound_margin: float = 1.0  # metres added around the first frame's points (and around later growth)
    max_extent: float = 60.0  # metres per axis a growing map may reach (stops runaway growth from stray depth)
    # Without a ground-truth first pose and without `bound`: the map frame is the first camera's turned so that the
    # scene's walls and floor are parallel to the feature planes (mapping/map_frame.py; ICL office 0.23 cm squared
    # against 1.1-1.2 cm turned 30 degrees). False: the first camera's frame as it is.
    align_axes: bool = True

    def validate(self, check) -> None:
        if self.bound is not None:
            ok = (len(self.bound) == 2 and all(len(c) == 3 for c in self.bound)
                  and all(isinstance(v, (int, float)) for c in self.bound for v in c))
            check(ok, "scene.bound", "must be [[xmin, ymin, zmin], [xmax, ymax, zmax]]")
            check(all(self.bound[0][i] < self.bound[1][i] for i in range(3)), "scene.bound",
                  "each minimum must be smaller than its maximum")
        check(self.bound_margin >= 0.0, "scene.bound_margin", "must be >= 0")
        check(self.max_extent > 0.0, "scene.max_extent", "must be positive (metres per axis)")


@dataclass
class ModelConfig:
    truncation: float = 0.06  # T, metres
    coarse_resolution: float = 0.24  # cell size of the coarse geometry and appearance planes
    fine_geometry_resolution: float = 0.06
    fine_appearance_resolution: float = 0.03
    channels: int = 32
    # The paper says one hidden layer of 32; the official implementation uses two hidden layers of 16. We follow the
    # implementation, whose numbers the paper reports.
    decoder_hidden: int = 16
    decoder_layers: int = 2
    beta_init: float = 10.0  # sharpness of the SDF-to-density conversion
    learn_beta: bool = True  # fixed on TUM in the official configuration
    plane_init_std: float = 0.01

    def validate(self, check) -> None:
        check(self.truncation > 0, "model.truncation", "must be positive (metres)")
        for name in ("coarse_resolution", "fine_geometry_resolution", "fine_appearance_resolution"):
            check(getattr(self, name) > 0, f"model.{name}", "must be positive (metres)")
        check(self.fine_geometry_resolution <= self.coarse_resolution, "model.fine_geometry_resolution",
              "the fine plane must not be coarser than the coarse plane")
        check(self.fine_appearance_resolution <= self.coarse_resolution, "model.fine_appearance_resolution",
              "the fine plane must not be coarser than the coarse plane")
        check(self.channels > 0, "model.channels", "must be positive")
        check(self.decoder_hidden > 0 and self.decoder_layers >= 1, "model.decoder_hidden",
              "decoders need at least one hidden layer of positive width")
        check(self.beta_init > 0, "model.beta_init", "must be positive")
        check(self.plane_init_std >= 0, "model.plane_init_std", "must be >= 0")


@dataclass
class RenderConfig:
    n_stratified: int = 32
    n_importance: int = 8  # near-surface samples (uniform in d +- surface_band*T), importance samples without depth
    depth_far_factor: float = 1.2  # stratified samples span [0, factor * depth]
    surface_band: float = 1.5  # in units of the truncation

    def validate(self, check) -> None:
        check(self.n_stratified >= 2, "render.n_stratified", "needs at least 2 samples")
        check(self.n_importance >= 0, "render.n_importance", "must be >= 0")
        check(self.depth_far_factor >= 1.0, "render.depth_far_factor", "must be >= 1")
        check(self.surface_band > 0, "render.surface_band", "must be positive")


@dataclass
class LossWeights:
    free_space: float = 5.0
    truncation_center: float = 200.0
    truncation_tail: float = 10.0
    depth: float = 0.1
    color: float = 5.0

    def validate(self, check, where: str) -> None:
        for f in dataclasses.fields(self):
            check(getattr(self, f.name) >= 0, f"{where}.{f.name}", "loss weights must be >= 0")


@dataclass
class TrackingConfig:
    """The front end, and what both trackers share."""
    # "render": the paper's tracker, Adam on the rendering losses (render_tracker section). "sdf": Gauss-Newton
    # alignment of the back-projected depth to the map's SDF (sdf_tracker section; one SDF query per pixel instead of
    # a rendered ray; the `fast` preset).
    method: str = "render"
    # "track": every frame is tracked against the map. "external": frames take their pose from the external
    # odometry (Frame.odom_pose, expressed in the map frame by the first frame) and are not tracked: mapping only.
    mode: str = "track"
    iterations: int = 8
    rays: int = 2000  # rays (render) or depth points (sdf) per iteration
    border: int = 75  # pixels ignored at the image border
    constant_velocity: bool = True

    def validate(self, check) -> None:
        check(self.method in ("render", "sdf"), "tracking.method", "must be 'render' or 'sdf'")
        check(self.mode in ("track", "external"), "tracking.mode",
              "must be 'track' or 'external' (poses from external odometry, mapping only)")
        check(self.iterations >= 0, "tracking.iterations", "must be >= 0")
        check(self.rays > 0, "tracking.rays", "must be positive")
        check(self.border >= 0, "tracking.border", "must be >= 0")


@dataclass
class RenderTrackerConfig:
    """The paper's rendering tracker (tracking.method render): Adam on the rendering losses."""
    lr_rotation: float = 0.001
    lr_translation: float = 0.002
    outlier_factor: float = 10.0  # drop rays whose depth error exceeds this times the batch median
    # Draw rays only from pixels whose depth point (at the predicted pose) lies in observed space, where the map has
    # been fitted (observed.py), unless that leaves fewer than half of them. Off in the paper.
    observed_only: bool = False
    weights: LossWeights = field(default_factory=lambda: LossWeights(10.0, 200.0, 50.0, 1.0, 5.0))

    def validate(self, check) -> None:
        check(self.lr_rotation >= 0 and self.lr_translation >= 0, "render_tracker.lr_rotation", "must be >= 0")
        check(self.outlier_factor > 0, "render_tracker.outlier_factor", "must be positive")
        self.weights.validate(check, "render_tracker.weights")


@dataclass
class SDFTrackerConfig:
    """The SDF tracker (tracking.method sdf, sdf_tracker.py): robust scales of its geometric (metres) and map-colour
    (grey level in [0, 1]) residuals and the weight of the latter (0 = not used); the same for its photometric
    residual against the newest keyframe's images, aligned coarse to fine over `pyramid_levels` image levels
    (photometric.py)."""
    huber: float = 0.01
    color_huber: float = 0.1
    color_weight: float = 1.0
    photometric_huber: float = 0.05
    photometric_weight: float = 1.0
    pyramid_levels: int = 3
    # It aligns to the surface of keyframes followed by this many mapped keyframes (settled space, observed.py): one
    # mapping step leaves new surface rough and the steps of the next keyframes, whose windows hold it, finish the
    # fit. Where settled space holds under half of the frame's points in observed space (the camera turns to new
    # space faster than it settles) it aligns to all of those. `live`, lock-step on the 300 ICL frames: ATE 0.42 cm
    # with 1, 0.17 with 3; 7-Scenes 3.16 / 3.19 cm (session 19, README).
    observed_after: int = 3

    def validate(self, check) -> None:
        check(self.huber > 0, "sdf_tracker.huber", "must be positive (metres)")
        check(self.observed_after >= 1, "sdf_tracker.observed_after",
              "must be >= 1 (1: the tracker aligns to all of observed space)")
        check(self.color_huber > 0, "sdf_tracker.color_huber", "must be positive (grey level)")
        check(self.color_weight >= 0, "sdf_tracker.color_weight", "must be >= 0 (0 disables the map's colour term)")
        check(self.photometric_huber > 0, "sdf_tracker.photometric_huber", "must be positive (grey level)")
        check(self.photometric_weight >= 0, "sdf_tracker.photometric_weight",
              "must be >= 0 (0 disables the keyframe photometric term)")
        check(1 <= self.pyramid_levels <= 6, "sdf_tracker.pyramid_levels", "must be between 1 and 6")


@dataclass
class OdometryConfig:
    """The starting pose from frame-to-frame RGB-D odometry (tracking/odometry.py) on images about `width` pixels
    wide, where it succeeds, instead of the constant-velocity prediction; width 0 = constant velocity only (the
    paper)."""
    width: int = 0
    # Its Gauss-Newton iterations per pyramid level, the finest level first (OpenCV's default: 7, 7, 7, 10).
    iterations: list[int] = field(default_factory=lambda: [7, 7, 7, 10])

    def validate(self, check) -> None:
        check(self.width == 0 or self.width >= 64, "odometry.width",
              "must be 0 (off) or at least 64 pixels (the odometry's image pyramid needs 4 levels)")
        check(len(self.iterations) == 4 and all(isinstance(n, int) and not isinstance(n, bool) and n >= 1
                                                for n in self.iterations),
              "odometry.iterations", "must be 4 positive integers (iterations per level, finest first)")


# Keys that moved to the section of the part that reads them: (old section, old key) -> new "section.key".
MOVED_KEYS = {
    **{("tracking", k): f"render_tracker.{k}" for k in ("lr_rotation", "lr_translation", "outlier_factor",
                                                        "observed_only", "weights")},
    **{("tracking", k): f"sdf_tracker.{k}" for k in ("huber", "color_huber", "color_weight", "photometric_huber",
                                                     "photometric_weight", "pyramid_levels", "observed_after")},
    ("tracking", "odometry_width"): "odometry.width",
    ("tracking", "odometry_iterations"): "odometry.iterations",
}


@dataclass
class MappingConfig:
    every: int = 4  # a keyframe (and a mapping step) every this many frames
    iterations: int = 15
    rays: int = 4000
    window: int = 20  # W: current frame + last two keyframes + W-3 overlapping keyframes
    first_iterations: int = 1000
    first_lr_factor: float = 5.0
    lr_planes: float = 0.005
    lr_decoders: float = 0.001
    lr_poses: float = 0.001
    # Window keyframe poses are optimised jointly with the map (the paper) once this many keyframes exist.
    joint_poses: bool = True
    joint_poses_after: int = 4
    border: int = 0
    weights: LossWeights = field(default_factory=LossWeights)
    # The keyframe store's memory budget (MB): over it, old keyframes keep 1/16 of their pixels, then the most
    # redundant ones are dropped (mapping/keyframes.py). 0 = no budget. Sized for a 2-core / 24 GB robot computer.
    keyframe_budget_mb: float = 512.0

    def validate(self, check) -> None:
        check(self.every >= 1, "mapping.every", "must be >= 1")
        check(self.keyframe_budget_mb >= 0, "mapping.keyframe_budget_mb", "must be >= 0 (0 = no budget)")
        check(self.iterations >= 0 and self.first_iterations >= 0, "mapping.iterations", "must be >= 0")
        check(self.rays > 0, "mapping.rays", "must be positive")
        check(self.window >= 3, "mapping.window", "must be >= 3 (current frame + last two keyframes)")
        check(self.first_lr_factor > 0, "mapping.first_lr_factor", "must be positive")
        check(min(self.lr_planes, self.lr_decoders, self.lr_poses) >= 0, "mapping.lr_planes", "must be >= 0")
        check(self.border >= 0, "mapping.border", "must be >= 0")
        self.weights.validate(check, "mapping.weights")


@dataclass
class MeshConfig:
    resolution: float = 0.02  # marching-cubes voxel size (metres); re-mesh finer from a checkpoint
    enabled: bool = True

    def validate(self, check) -> None:
        check(self.resolution > 0, "mesh.resolution", "must be positive (metres)")


@dataclass
class RunConfig:
    seed: int = 0
    threads: int = 0  # torch threads (0 = torch's default)
    # "slam": track and map. "localization": track and relocalize against a loaded, frozen map (no mapping).
    mode: str = "slam"
    # Where the map, tracking, mapping and rendering run (eslam_core/device.py): auto (a CUDA GPU when torch sees
    # one, else the CPU), cpu, cuda or cuda:N. Checked against this machine when the config is loaded.
    device: str = "auto"

    def validate(self, check) -> None:
        from eslam_core.device import device_problem  # (imports torch: only when a config is validated)

        check(self.threads >= 0, "run.threads", "must be >= 0")
        check(self.mode in ("slam", "localization"), "run.mode", "must be 'slam' or 'localization'")
        problem = device_problem(self.device)
        check(problem is None, "run.device", problem or "")


@dataclass
class QualityConfig:
    """When a tracked frame counts as lost (tracking/quality.py)."""

    enabled: bool = True  # off: no frame ever counts as lost (the quality is still computed and reported)

    depth_low: float = 0.05  # fraction of pixels with depth where the depth score is 0 ...
    depth_high: float = 0.25  # ... and where it reaches 1
    inliers_low: float = 0.2  # inlier fraction where the inlier score is 0 ...
    inliers_high: float = 0.6  # ... and 1
    residual_high: float = 2.0  # loss / typical loss where the residual score starts to fall ...
    residual_low: float = 4.0  # ... and where it is 0
    residual_observed_below: float = 0.7  # the residual counts only when fewer of the points are in observed space
    correction_m: float = 0.15  # correction of the prediction per frame gap where the motion score starts to fall
    correction_deg: float = 15.0  # (it is 0 at twice these)
    # While lost, a pose counts only where the map is: the share of depth points in observed space where the
    # "mapped" score is 0 and where it is 1. A pose that puts most of the view in unmapped space is a guess, however
    # well its few mapped points fit (7-Scenes restart: 25 % observed, 95 % of those fitting, 80 cm off), while a
    # view half of which is new is not (ICL restart near the map's edge: 41-45 % observed, right to 3 mm).
    found_observed_low: float = 0.15
    found_observed_high: float = 0.35
    # A pose whose covariance (tracking/information.py) has a position axis beyond `degraded_sigma_m` or a rotation
    # axis beyond `degraded_sigma_deg` is degraded: the view leaves it free in some direction (quality.py).
    degraded_sigma_m: float = 0.02
    degraded_sigma_deg: float = 2.0
    lost_below: float = 0.5
    found_above: float = 0.7

    def validate(self, check) -> None:
        check(0 <= self.depth_low < self.depth_high <= 1, "quality.depth_low",
              "needs 0 <= depth_low < depth_high <= 1 (fractions of the pixels)")
        check(0 <= self.inliers_low < self.inliers_high <= 1, "quality.inliers_low",
              "needs 0 <= inliers_low < inliers_high <= 1 (fractions of the points)")
        check(1 <= self.residual_high < self.residual_low, "quality.residual_high",
              "needs 1 <= residual_high < residual_low (ratios to the typical loss)")
        check(self.correction_m > 0 and self.correction_deg > 0, "quality.correction_m",
              "correction_m and correction_deg must be positive")
        check(0 <= self.found_observed_low < self.found_observed_high <= 1, "quality.found_observed_low",
              "needs 0 <= found_observed_low < found_observed_high <= 1 (fractions of the points)")
        check(0 < self.lost_below <= self.found_above <= 1, "quality.lost_below",
              "needs 0 < lost_below <= found_above <= 1")
        check(self.degraded_sigma_m > 0 and self.degraded_sigma_deg > 0, "quality.degraded_sigma_m",
              "degraded_sigma_m and degraded_sigma_deg must be positive")


@dataclass
class RelocalizationConfig:
    """Finding a lost camera again against the keyframes (tracking/relocalization.py)."""

    enabled: bool = True
    features: int = 1000  # ORB keypoints per image
    # FAST corner thresholds (grey levels), ORB-SLAM's: an image giving under half the keypoints at the first is
    # searched again at the second, which also finds corners in smooth texture, not only on object outlines (where
    # the depth of a corner is ambiguous and a keyframe feature is dropped).
    fast_threshold: int = 20
    fast_threshold_min: int = 7
    thumbnail_width: int = 40  # PTAM's small blurry image: 40 x 30 for 4:3 images ...
    thumbnail_blur: float = 2.5  # ... blurred with this sigma, in thumbnail pixels
    words: int = 1000  # size of the binary vocabulary (at most one word per 20 keyframe descriptors)
    # Place recognition: "both" verifies the best keyframes of each ranking in turn, best thumbnail first.
    retrieval: str = "both"  # both | thumbnail | words
    candidates: int = 3  # keyframes verified geometrically per frame, from each ranking
    enough_inliers: int = 100  # stop verifying candidates once one keyframe gives this many inliers
    ratio: float = 0.8  # Lowe's ratio test on the Hamming distances of the two nearest keyframe features
    reprojection_px: float = 4.0  # PnP RANSAC inlier threshold at 640 pixels wide (scaled with the image width)
    # Noise of the refinement's residuals: keypoint position (pixels at 640 wide), and measured depth as a
    # Kinect-like sensor's: sigma(z) = base + quadratic * (z - 0.4 m)^2 (Nguyen et al. 2012).
    pixel_sigma: float = 1.0
    depth_sigma_base: float = 0.0012
    depth_sigma_quadratic: float = 0.0019
    min_inliers: int = 25  # PnP inliers needed to accept a pose ...
    min_inlier_ratio: float = 0.25  # ... and inliers / matches
    depth_sigmas: float = 3.0  # a feature agrees with the measured depth within this many sigma(z)
    min_depth_agreement: float = 0.5  # fraction of the reprojected features with measured depth that must agree
    edge_tolerance: float = 0.05  # a keypoint whose 3x3 depths spread over more than this * depth is on an edge
    # The map checked against itself (tracking/map_check.py): each new keyframe is placed by the features of
    # keyframes at least `map_check_gap` older (0: no check); the map disagrees where that place and the tracked
    # pose are more than `map_disagree_m` or `map_disagree_deg` apart. `fast` lock-step, the checks that found a
    # match: ICL office kt0 300 frames, 16, at most 9.2 cm / 1.5 deg apart; 7-Scenes RedKitchen 400 frames, 9, at
    # most 8.1 cm / 2.2 deg (its drift and PnP's error on Kinect frames); a slide of the synthetic two planes 48 cm.
    map_check_gap: int = 20
    map_disagree_m: float = 0.20
    map_disagree_deg: float = 10.0
    # A camera that is not lost (its view left some direction free, or it waits to be anchored again) takes a
    # relocalization at most this far from its predicted position; one farther is another place that looks alike
    # (the generated corridor loop's corners: a jump of 6.5 m, every later pose wrong). A lost camera takes any.
    # The map check, too, ignores a placement farther than this from the tracked pose (the generated flat's rooms
    # share their furniture: keyframes placed 2-8 m away, turned 90-180 degrees).
    max_jump_m: float = 1.0

    def validate(self, check) -> None:
        check(self.features >= 50, "relocalization.features", "must be >= 50 (ORB keypoints per image)")
        check(1 <= self.fast_threshold_min <= self.fast_threshold <= 100, "relocalization.fast_threshold",
              "needs 1 <= fast_threshold_min <= fast_threshold <= 100 (grey levels)")
        check(self.thumbnail_width >= 8, "relocalization.thumbnail_width", "must be >= 8 pixels")
        check(self.thumbnail_blur >= 0, "relocalization.thumbnail_blur", "must be >= 0 (thumbnail pixels)")
        check(self.words >= 16, "relocalization.words", "must be >= 16")
        check(self.retrieval in ("both", "thumbnail", "words"), "relocalization.retrieval",
              "must be 'both', 'thumbnail' or 'words'")
        check(self.candidates >= 1, "relocalization.candidates", "must be >= 1")
        check(self.enough_inliers >= self.min_inliers, "relocalization.enough_inliers", "must be >= min_inliers")
        check(self.map_check_gap >= 0, "relocalization.map_check_gap", "must be >= 0 keyframes (0: no map check)")
        check(self.max_jump_m > 0, "relocalization.max_jump_m", "must be positive (metres)")
        check(self.map_disagree_m > 0 and self.map_disagree_deg > 0, "relocalization.map_disagree_m",
              "map_disagree_m and map_disagree_deg must be positive")
        check(0 < self.ratio <= 1, "relocalization.ratio", "must be in (0, 1]")
        check(self.reprojection_px > 0, "relocalization.reprojection_px", "must be positive (pixels)")
        check(self.pixel_sigma > 0 and self.depth_sigma_base > 0 and self.depth_sigma_quadratic >= 0,
              "relocalization.pixel_sigma", "pixel_sigma and depth_sigma_base must be positive, "
              "depth_sigma_quadratic >= 0")
        check(self.min_inliers >= 6, "relocalization.min_inliers", "must be >= 6 (PnP needs at least 4)")
        check(0 <= self.min_inlier_ratio <= 1, "relocalization.min_inlier_ratio", "must be in [0, 1]")
        check(self.depth_sigmas > 0, "relocalization.depth_sigmas", "must be positive")
        check(self.edge_tolerance > 0, "relocalization.edge_tolerance", "must be positive (fraction of depth)")
        check(0 <= self.min_depth_agreement <= 1, "relocalization.min_depth_agreement", "must be in [0, 1]")


@dataclass
class RuntimeConfig:
    """Tuning of the runtimes (eslam_core/runtime): how `eslam run --workers 2` and the ROS node run SLAM."""

    capacity: int = 8  # frames in the input buffer
    # Live policy: frames that may wait behind the one the tracker takes before it skips to the newest (0: always
    # the newest). With 1, a frame that one spike of work made late is tracked a frame period later instead of
    # dropped (README, "Maps without edges, and memory that stays flat": the hour live).
    live_backlog: int = 1
    # Offline runs through the runtime (`eslam run --workers 2`): frames decoded ahead, beyond the input buffer, by
    # a thread that only gets CPU time no other work wants (datasets/read_ahead.py; 0 = none). About 2 MB a
    # 640 x 480 frame. `fast` on the 300 ICL office frames, runs alternating (README, session 20): 21.8-26.9
    # frames/s without (median 25.4, 11 runs), 25.1-27.4 with 64 (median 27.1, 7 runs).
    read_ahead: int = 64
    # Pipelined mapper: optimiser iterations between mid-step map publications (0 = only after each step). A step
    # starts a new Adam, whose first iterations move every touched feature by about the learning rate: read
    # mid-step, a converged map is jittered. On ICL played back and forth (4-minute soaks) publishing every 5
    # iterations left frames 275-277 5-8 cm off in later forward laps, worst lap 1.3-1.9x the first; after each
    # step only, at most 4.5 cm and 1.15x (over 20 minutes forward laps still reached 1.5 cm: README, soak).
    publish_every: int = 0
    lend_threads: bool = True  # pipelined: an idle worker's torch threads go to the busy one
    # Pipelined, offline policy: keyframes that may wait for the mapper before the older ones join the newest
    # one's window without a step of their own (None = every keyframe gets its step; the live policy uses 0).
    keyframe_backlog: Optional[int] = None
    # Pipelined: once newer keyframes wait, a mapping step ends after this many iterations divided by their
    # number (None = never), so that the mapper stays within about a keyframe of the tracker.
    catch_up_iterations: Optional[int] = None
    # Pipelined, offline policy: the tracker waits while more keyframes than this wait to be mapped (None = never).
    # A tracker faster than the mapper otherwise runs ahead without limit: on 300 ICL frames the map it tracked
    # against lagged 34 keyframes behind, and on a long run the mapper's queue of keyframes grows with time.
    max_keyframe_lag: Optional[int] = 4
    # Pipelined, live policy: a mapping step goes on up to this many iterations while no newer keyframe waits: the
    # mapper's idle time between keyframes (a keyframe that arrives ends it once it has had mapping.iterations).
    # None = mapping.iterations. Offline the tracker waits for the mapper, which has no idle time.
    idle_iterations: Optional[int] = None
    # Pipelined: the tracker gets the first map after this many of the warm-up's iterations (null = after all of
    # them) and tracks while the warm-up goes on, instead of waiting with its core lent to the warm-up (two threads
    # on the warm-up's small tensors are only ~1.2x one). The first frames are then tracked against a map of the
    # first keyframe that is still converging, mostly held by the odometry and the photometric term on that same
    # keyframe.
    first_map_after: Optional[int] = None
    # Pipelined: the mapping process's niceness (0-19). Tracking sets the pose latency and mapping can catch up
    # later (its steps are cut short while keyframes wait), so on a machine short of cores the mapper gets the
    # time that tracking and the node leave.
    mapper_nice: int = 10

    def validate(self, check) -> None:
        check(self.capacity >= 1, "runtime.capacity", "must be >= 1")
        check(0 <= self.live_backlog < self.capacity, "runtime.live_backlog",
              f"must be >= 0 frames and below runtime.capacity ({self.capacity})")
        check(self.read_ahead >= 0, "runtime.read_ahead", "must be >= 0 frames (0 = no read-ahead)")
        check(self.publish_every >= 0, "runtime.publish_every", "must be >= 0 (0 = only after each step)")
        check(self.keyframe_backlog is None or self.keyframe_backlog >= 0, "runtime.keyframe_backlog",
              "must be >= 0, or null for no limit")
        check(self.catch_up_iterations is None or self.catch_up_iterations >= 1, "runtime.catch_up_iterations",
              "must be >= 1, or null for never")
        check(self.idle_iterations is None or self.idle_iterations >= 1, "runtime.idle_iterations",
              "must be >= 1, or null for mapping.iterations")
        check(self.max_keyframe_lag is None or self.max_keyframe_lag >= 0, "runtime.max_keyframe_lag",
              "must be >= 0, or null for no limit")
        check(self.first_map_after is None or self.first_map_after >= 1, "runtime.first_map_after",
              "must be >= 1 (warm-up iterations), or null for after the whole warm-up")
        check(0 <= self.mapper_nice <= 19, "runtime.mapper_nice", "must be a niceness from 0 to 19")


@dataclass
class SubmapConfig:
    """The scene as several local maps and loop closure between them (submaps/atlas.py; not part of the paper)."""

    # A keyframe farther than this from its submap's anchor (where the camera was when the submap began) goes to
    # the nearest other submap within it, or starts a new one there. 0: one map, the paper's (it grows with the
    # space it covers).
    radius_m: float = 0.0
    # Close loops: a keyframe placed by the keyframes of another submap (the map check's PnP, map_check.py) is an
    # edge of the pose graph over the submaps' anchors; the graph is solved and the submaps move rigidly.
    loop_closure: bool = True
    # The drift allowed between two consecutive submaps' anchors, per metre between them (the information of the
    # graph's odometry edges; a loop whose correction exceeds what this allows is refused as an outlier).
    drift_m_per_m: float = 0.03
    drift_deg_per_m: float = 1.5

    def validate(self, check) -> None:
        check(self.radius_m == 0.0 or self.radius_m >= 1.0, "submaps.radius_m",
              "must be 0 (one map) or at least 1 m (a submap must hold a few keyframes' views)")
        check(self.drift_m_per_m > 0.0 and self.drift_deg_per_m > 0.0, "submaps.drift_m_per_m",
              "drift_m_per_m and drift_deg_per_m must be positive")


@dataclass
class Config:
    name: str = "eslam"
    camera: CameraConfig = field(default_factory=CameraConfig)
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    render_tracker: RenderTrackerConfig = field(default_factory=RenderTrackerConfig)
    sdf_tracker: SDFTrackerConfig = field(default_factory=SDFTrackerConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    run: RunConfig = field(default_factory=RunConfig)
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)
    quality: QualityConfig = field(default_factory=QualityConfig)
    relocalization: RelocalizationConfig = field(default_factory=RelocalizationConfig)
    submaps: SubmapConfig = field(default_factory=SubmapConfig)

    def validate(self, source: str = "<config>") -> "Config":
        def check(ok: bool, key: str, message: str) -> None:
            if not ok:
                raise ConfigError(f"{source}: invalid value for '{key}': {message}")

        for f in dataclasses.fields(self):
            section = getattr(self, f.name)
            if dataclasses.is_dataclass(section):
                section.validate(check)
        check(self.submaps.radius_m == 0.0 or self.scene.bound is None, "submaps.radius_m",
              "submaps need a map that grows (scene.bound null): each covers its own part of the space")
        return self

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


# ---------------------------------------------------------------------------------------------------------- loading

PRESET_DIRS = [Path(__file__).resolve().parent.parent / "config"]


def preset_path(name: str) -> Path:
    """Path of a shipped preset (`replica`, `icl`, ...), looked up in the source tree or the installed package."""
    for d in PRESET_DIRS:
        p = d / f"{name}.yaml"
        if p.exists() and _is_preset(p.read_text()):
            return p
    packaged = resources.files("eslam_core") / "presets" / f"{name}.yaml"
    if packaged.is_file() and _is_preset(packaged.read_text()):
        return Path(str(packaged))
    raise ConfigError(f"unknown preset '{name}': give a path to a YAML file or one of {', '.join(list_presets())}")


def _is_preset(text: str) -> bool:
    return "ros__parameters" not in text  # config/ also holds the ROS node's parameter file


def list_presets() -> list[str]:
    names = set()
    for d in PRESET_DIRS:
        names.update(p.stem for p in d.glob("*.yaml") if _is_preset(p.read_text()))
    packaged = resources.files("eslam_core") / "presets"
    if packaged.is_dir():
        names.update(Path(p.name).stem for p in packaged.iterdir()
                     if p.name.endswith(".yaml") and _is_preset(p.read_text()))
    return sorted(names)


def _deep_merge(base: dict, override: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in override.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def _read_yaml(path: Path, chain: tuple = ()) -> dict:
    """The file's mapping with its `extends:` parents merged in (parents first)."""
    if path in chain:
        raise ConfigError(f"{path}: 'extends' forms a cycle: {' -> '.join(str(p) for p in chain + (path,))}")
    if not path.exists():
        raise ConfigError(f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise ConfigError(_yaml_error_line(path, e)) from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of sections (camera:, model:, ...)")
    parent = data.pop("extends", None)
    if parent is None:
        return data
    parent_path = (path.parent / parent) if str(parent).endswith((".yaml", ".yml")) else preset_path(str(parent))
    return _deep_merge(_read_yaml(parent_path.resolve(), chain + (path,)), data)


def _yaml_error_line(path: Path, e: Exception) -> str:
    """The parser's multi-line report as one line: file:line:column, the problem, what to fix."""
    if isinstance(e, UnicodeDecodeError):
        return f"{path}: not valid YAML: not UTF-8 text (byte {e.start}) (fix the file: a config is a text file)"
    mark = getattr(e, "problem_mark", None)
    where = f"{path}:{mark.line + 1}:{mark.column + 1}" if mark is not None else str(path)
    problem = getattr(e, "problem", None) or " ".join(str(e).split())
    context, context_mark = getattr(e, "context", None), getattr(e, "context_mark", None)
    # An unclosed bracket or quote is found where the file ends: where it opened is what helps.
    opened = f"; {context} from line {context_mark.line + 1}" if context and context_mark is not None else ""
    return f"{where}: not valid YAML: {problem} (fix the file there{opened})"


def _coerce(value: Any, tp: Any, key: str, source: str) -> Any:
    """Check `value` against the annotation `tp`, converting ints to floats where a float is expected."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _coerce(value, args[0], key, source)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{source}: '{key}' must be a mapping, got {type(value).__name__}")
        return _build(tp, value, key, source)
    if tp is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if tp is list or origin is list:
        if not isinstance(value, list):
            raise ConfigError(f"{source}: '{key}' must be a list, got {type(value).__name__}")
        return value
    if tp in (int, float, str, bool):
        if not isinstance(value, tp) or (tp is int and isinstance(value, bool)):
            raise ConfigError(f"{source}: '{key}' must be of type {tp.__name__}, got {value!r}")
        return value
    return value


def _build(cls, data: dict, prefix: str, source: str):
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        where = f"{prefix}." if prefix else ""
        raise ConfigError(f"{source}: unknown key '{where}{unknown[0]}' (known keys here: {', '.join(sorted(names))})")
    kwargs = {}
    for name, value in data.items():
        key = f"{prefix}.{name}" if prefix else name
        kwargs[name] = _coerce(value, hints[name], key, source)
    return cls(**kwargs)


def moved_keys(data: dict, source: str, migrate: bool) -> dict:
    """`data` with the keys of MOVED_KEYS at their new place (`migrate`: a checkpoint's own config), or a
    ConfigError naming the first old key and its new name (a user's file or override)."""
    data = copy.deepcopy(data)
    for (section, key), new in MOVED_KEYS.items():
        old = data.get(section)
        if not isinstance(old, dict) or key not in old:
            continue
        if not migrate:
            raise ConfigError(f"{source}: '{section}.{key}' is now '{new}' (each section of the config belongs to "
                              f"the part that reads it); rename it")
        new_section, new_key = new.split(".")
        data.setdefault(new_section, {})[new_key] = old.pop(key)
    return data


def config_from_dict(data: dict, source: str = "<dict>", migrate: bool = False) -> Config:
    """`migrate`: move the keys of an older layout (MOVED_KEYS) instead of refusing them."""
    return _build(Config, moved_keys(data, source, migrate), "", source).validate(source)


def load_config(path_or_preset: str | Path, overrides: Optional[dict] = None) -> Config:
    """Load a YAML file (or a shipped preset by name), apply `overrides` (nested dict), validate."""
    p = Path(path_or_preset)
    if not p.exists() and p.suffix not in (".yaml", ".yml"):
        p = preset_path(str(path_or_preset))
    data = _read_yaml(p.resolve())
    if overrides:
        data = _deep_merge(data, overrides)
    return config_from_dict(data, str(p))


def save_config(config: Config, path: Path) -> None:
    write_atomic(path, yaml.safe_dump(config.to_dict(), sort_keys=False))
