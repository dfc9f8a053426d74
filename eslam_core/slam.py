"""The SLAM system: the map, the keyframe list and the trajectory, advanced one frame at a time.

This is the single-process, lock-step schedule of the method: track every frame against the current map, and every
`mapping.every` frames make the frame a keyframe and run a mapping step. Refined keyframe poses are written back into
the trajectory: each frame's pose is stored relative to the keyframe it was tracked after, so a keyframe correction
moves the frames that depend on it too.
"""
from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import torch

from eslam_core.mapping.extent import estimate_bound, grow_to_multiple, outside_mask
from eslam_core.camera import Frame, Intrinsics
from eslam_core.config import Config, config_from_dict
from eslam_core.cpu import keep_freed_memory
from eslam_core.representation.field import SceneField
from eslam_core.frames import PreparedFrame, pixel_directions_table, prepare_frame, working_intrinsics
from eslam_core.geometry import depth_points_world, interpolate_pose
from eslam_core.mapping.keyframes import Keyframe, select_window
from eslam_core.mapping.mapper import Mapper
from eslam_core.mapping.observed import ObservedSpace
from eslam_core.tracking.render_tracker import constant_velocity, make_tracker, time_ratio

log = logging.getLogger("eslam")

CHECKPOINT_VERSION = 2


@dataclass
class FrameRecord:
    index: int
    timestamp: float
    reference: int  # position of the keyframe this frame's pose is relative to
    relative: np.ndarray  # 4x4: pose = keyframes[reference].pose @ relative (before blending, see frame_pose)
    tracking_loss: float
    gt_pose: Optional[np.ndarray]
    tracked: np.ndarray  # 4x4: the pose when tracked (a keyframe's before mapping refined it)


def frame_pose(records: list[FrameRecord], keyframe_records: dict[int, int], keyframe_pose: Callable[[int], np.ndarray],
               k: int) -> np.ndarray:
    """The pose of frame `k` given the keyframe poses as mapping has refined them (`keyframe_records`: keyframe
    position -> its record). A frame moves with its keyframe's correction, blended (by time) into the next
    keyframe's correction as it nears that keyframe: tracking errors drift smoothly between keyframes, and mapping
    corrects them at the keyframes only."""
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


def keyframe_positions(records: list[FrameRecord]) -> dict[int, int]:
    """Keyframe position -> its own record (the first one that refers to it)."""
    positions: dict[int, int] = {}
    for k, r in enumerate(records):
        positions.setdefault(r.reference, k)
    return positions


@dataclass
class StepResult:
    index: int
    pose: np.ndarray
    tracking_loss: float
    keyframe: bool
    mapping_loss: float


class SLAM:
    def __init__(self, cfg: Config, intrinsics: Intrinsics):
        keep_freed_memory()  # process-wide, see cpu.py
        self.cfg = cfg
        self.input_intrinsics = intrinsics
        self.intr = working_intrinsics(intrinsics, cfg.camera)
        self.dirs_cam = pixel_directions_table(self.intr)
        self.tracker = make_tracker(cfg, self.dirs_cam, self.intr)
        self.mapper = Mapper(cfg, self.dirs_cam, self.intr.height, self.intr.width)
        self.field: Optional[SceneField] = None
        self.bound: Optional[np.ndarray] = None
        self.observed: Optional[ObservedSpace] = None
        self.unobserved: deque = deque()  # surface points of the keyframes not in observed space yet, oldest first
        self.observed_keyframes = 0
        self.keyframes: list[Keyframe] = []
        self.records: list[FrameRecord] = []
        self.keyframe_records: dict[int, int] = {}  # keyframe position -> its record
        self.points_outside = 0
        self.points_seen = 0
        self._warned_outside = 0.0
        self.stop_mapping_early: Optional[Callable[[int], bool]] = None  # see Mapper.map (set by the runtime)
        self.rng = np.random.default_rng(cfg.run.seed)

    # ------------------------------------------------------------------------------------------------ trajectory
    def pose(self, k: int) -> np.ndarray:
        return frame_pose(self.records, self.keyframe_records, self._keyframe_pose, k)

    def _keyframe_pose(self, i: int) -> np.ndarray:
        return self.keyframes[i].pose.double().numpy()

    def poses(self) -> np.ndarray:
        return np.stack([self.pose(k) for k in range(len(self.records))]) if self.records else np.zeros((0, 4, 4))

    def timestamps(self) -> np.ndarray:
        return np.array([r.timestamp for r in self.records])

    def gt_poses(self) -> list:
        return [r.gt_pose for r in self.records]

    # ---------------------------------------------------------------------------------------------------- frames
    def step(self, frame: Frame) -> StepResult:
        pf = prepare_frame(frame, self.input_intrinsics, self.cfg.camera)
        if self.field is None:
            return self._first_frame(pf)
        n = len(self.records)
        prev2 = self.pose(n - 2) if n >= 2 and self.cfg.tracking.constant_velocity else None
        ratio = time_ratio(self.records[n - 2].timestamp, self.records[n - 1].timestamp, pf.timestamp) if n >= 2 \
            else 1.0
        init = torch.from_numpy(constant_velocity(prev2, self.pose(n - 1), ratio)).float()
        # The bound test uses the predicted pose: a few centimetres off at most, and it saves a second pass.
        usable = self._usable_pixels(pf, init)
        result = self.tracker.track(self.field, pf, init, usable, self.observed, self.keyframes[-1])
        pose = result.pose
        if not torch.isfinite(pose).all():  # a diverged optimisation must not poison the trajectory and the map
            log.warning("frame %d: tracking diverged (non-finite pose); keeping the motion model's prediction",
                        pf.index)
            pose = init
        is_keyframe = n % self.cfg.mapping.every == 0
        mapping_loss = float("nan")
        if is_keyframe:
            self._add_keyframe(pf, usable, pose)
            self._record(pf, pose, result.loss, keyframe=True)
            mapping_loss = self._map_current()
        else:
            self._record(pf, pose, result.loss, keyframe=False)
        return StepResult(pf.index, self.pose(n), result.loss, is_keyframe, mapping_loss)

    def _record(self, pf: PreparedFrame, pose: torch.Tensor, loss: float, keyframe: bool) -> None:
        """Store a tracked frame relative to the newest keyframe (itself, when it is that keyframe)."""
        ref = len(self.keyframes) - 1
        tracked = pose.double().numpy()
        rel = np.eye(4) if keyframe else np.linalg.inv(self._keyframe_pose(ref)) @ tracked
        if keyframe:
            self.keyframe_records[ref] = len(self.records)
        self.records.append(FrameRecord(pf.index, pf.timestamp, ref, rel, loss, pf.gt_pose, tracked))

    def _first_frame(self, pf: PreparedFrame) -> StepResult:
        """Start the map from the first frame and map it alone (the warm-up)."""
        pose0 = self._start_map(pf)
        res = self.mapper.map(self.field, self.keyframes, [0], first=True)
        self.observe_mapped(1)
        return StepResult(pf.index, pose0, 0.0, True, res.loss)

    def _start_map(self, pf: PreparedFrame) -> np.ndarray:
        """Fix the first pose (ground truth when known, so outputs share its frame), set the bound, create the
        field and make the frame the first keyframe; returns the first pose. (The multi-process runtime's tracker
        calls this too and leaves the warm-up to its mapper process.)"""
        pose0 = pf.gt_pose if pf.gt_pose is not None else np.eye(4)
        self.bound = self._scene_bound(pf, pose0)
        self.field = SceneField(self.bound, self.cfg.model)
        self.observed = ObservedSpace(self.bound, self.cfg.model.truncation)
        log.info("map: %d parameters over bound %s", self.field.parameter_count(), np.round(self.bound, 3).tolist())
        pose = torch.from_numpy(pose0).float()
        self._add_keyframe(pf, self._usable_pixels(pf, pose), pose)
        self._record(pf, pose, 0.0, keyframe=True)
        return pose0

    def _add_keyframe(self, pf: PreparedFrame, usable: torch.Tensor, pose: torch.Tensor) -> None:
        self.keyframes.append(Keyframe.from_tensors(pf.index, pf.timestamp, pf.rgb, pf.depth, usable, pose))
        self.unobserved.append(self._surface_points(pf.depth, usable, pose))

    def observe_mapped(self, mapped: int) -> None:
        """The map is now fitted to the first `mapped` keyframes: their surface joins observed space, except the
        newest one's. Its single mapping step shares the rays with the whole window and leaves space seen for the
        first time rough; it joins after the next step. The first keyframe joins after its warm-up."""
        trusted = min(mapped, max(1, mapped - 1))
        while self.observed_keyframes < trusted and self.unobserved:
            self.observed.add(self.unobserved.popleft())
            self.observed_keyframes += 1

    def _surface_points(self, depth: torch.Tensor, usable: torch.Tensor, pose: torch.Tensor,
                        stride: int = 2) -> torch.Tensor:
        """A keyframe's surface points for the observed space (every `stride`-th pixel is plenty for 6 cm voxels)."""
        take = torch.zeros_like(usable)
        take[::stride, ::stride] = True
        flat = torch.nonzero((take & usable & (depth > 0)).reshape(-1)).squeeze(1)
        return depth_points_world(self.dirs_cam[flat], depth.reshape(-1)[flat], pose)

    def _scene_bound(self, pf: PreparedFrame, pose0: np.ndarray) -> np.ndarray:
        step = self.cfg.model.coarse_resolution
        if self.cfg.scene.bound is not None:
            return grow_to_multiple(np.array(self.cfg.scene.bound, dtype=np.float64), step)
        bound = estimate_bound(pf.depth.numpy(), self.intr, pose0, self.cfg.scene.bound_margin, step)
        log.info("scene bound estimated from the first frame (margin %.2f m): %s; set scene.bound in the config "
                 "if the camera will see beyond it", self.cfg.scene.bound_margin, np.round(bound, 2).tolist())
        return bound

    def _usable_pixels(self, pf: PreparedFrame, pose: torch.Tensor) -> torch.Tensor:
        """Pixels whose measured surface lies inside the bound; the others are left out and counted."""
        depth = pf.depth.reshape(-1)
        points = depth_points_world(self.dirs_cam, depth, pose)
        outside = outside_mask(points, self.bound) & (depth > 0)
        n_out, n_valid = int(outside.sum()), int((depth > 0).sum())
        self.points_outside += n_out
        self.points_seen += n_valid
        frac = n_out / max(n_valid, 1)
        if frac > 0.05 and frac > 2 * self._warned_outside:
            self._warned_outside = frac
            log.warning("frame %d: %.0f%% of its depth points lie outside the scene bound and are not mapped "
                        "(%d so far); set scene.bound (or a larger scene.bound_margin) in the config",
                        pf.index, 100 * frac, self.points_outside)
        return ~outside.reshape(pf.depth.shape)

    def _map_current(self) -> float:
        current = len(self.keyframes) - 1
        kf = self.keyframes[current]
        d = kf.depth_image().reshape(-1)
        with_depth = torch.nonzero(d > 0).squeeze(1)
        sample = with_depth[torch.randint(len(with_depth), (min(len(with_depth), 500),))] if len(with_depth) else \
            with_depth
        points = depth_points_world(self.dirs_cam[sample], d[sample], kf.pose)
        window = select_window(self.keyframes, current, points, self.intr, self.cfg.mapping.window, self.rng)
        mc = self.cfg.mapping
        optimise_poses = mc.joint_poses and len(self.keyframes) > mc.joint_poses_after
        res = self.mapper.map(self.field, self.keyframes, window, first=False, optimise_poses=optimise_poses,
                              stop_early=self.stop_mapping_early)
        for i, pose in res.refined.items():
            self.keyframes[i].pose = pose.float()
        self.observe_mapped(len(self.keyframes))
        return res.loss

    # ------------------------------------------------------------------------------------------------ checkpoint
    def state_dict(self) -> dict:
        return {
            "version": CHECKPOINT_VERSION,
            "config": self.cfg.to_dict(),
            "intrinsics": self.input_intrinsics.__dict__,
            "bound": None if self.bound is None else torch.from_numpy(self.bound),
            "field": self.field.state_dict() if self.field is not None else None,
            "keyframes": [dict(kf.__dict__) for kf in self.keyframes],
            # Tensors, not numpy arrays, so that checkpoints load with torch.load(weights_only=True).
            "records": [dict(r.__dict__, relative=torch.from_numpy(r.relative), tracked=torch.from_numpy(r.tracked),
                             gt_pose=None if r.gt_pose is None else torch.from_numpy(r.gt_pose))
                        for r in self.records],
            "points_outside": self.points_outside,
            "points_seen": self.points_seen,
            "rng": self.rng.bit_generator.state,
        }

    @staticmethod
    def from_state_dict(state: dict) -> "SLAM":
        if state.get("version") != CHECKPOINT_VERSION:
            raise ValueError(f"checkpoint version {state.get('version')} is not supported (expected "
                             f"{CHECKPOINT_VERSION}); re-run `eslam run` to produce a new checkpoint")
        slam = SLAM(config_from_dict(state["config"], "checkpoint"), Intrinsics(**state["intrinsics"]))
        slam.bound = state["bound"].numpy() if state["bound"] is not None else None
        if state["field"] is not None:
            slam.field = SceneField(slam.bound, slam.cfg.model)
            slam.field.load_state_dict(state["field"])
            slam.observed = ObservedSpace(slam.bound, slam.cfg.model.truncation)
        slam.keyframes = [Keyframe(**kf) for kf in state["keyframes"]]
        for kf in slam.keyframes:
            slam.unobserved.append(slam._surface_points(kf.depth_image(), kf.usable, kf.pose) if kf.depth.numel()
                                   else torch.zeros(0, 3))
        if slam.observed is not None:
            slam.observe_mapped(len(slam.keyframes))
        slam.records = [FrameRecord(**dict(r, relative=r["relative"].numpy(), tracked=r["tracked"].numpy(),
                                           gt_pose=None if r["gt_pose"] is None else r["gt_pose"].numpy()))
                        for r in state["records"]]
        slam.keyframe_records = keyframe_positions(slam.records)
        slam.points_outside = state["points_outside"]
        slam.points_seen = state["points_seen"]
        slam.rng.bit_generator.state = state["rng"]
        return slam
