"""The scene map: where the map is (its extent, and how it grows), the field over it, the keyframe store, observed
space, and the mapping step that fits the field to the keyframes.

The extent starts as `scene.bound` (then a hard limit) or around the first frame. Without a configured bound it
grows by whole coarse cells wherever a new keyframe's depth falls outside it (up to `scene.max_extent` per axis):
the planes of both fields and both scales are extended, existing features stay where they are, and every growth is
a new field object (the pipelined runtime publishes it as a new map). Depth the map cannot cover is counted.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable, Optional

import numpy as np
import torch

from eslam_core.camera import Intrinsics
from eslam_core.config import Config
from eslam_core.cpu import flat_nonzero
from eslam_core.device import resolve_device
from eslam_core.frames import PreparedFrame
from eslam_core.geometry import depth_points_world
from eslam_core.mapping.consistency import keyframe_consistency
from eslam_core.mapping.extent import estimate_bound, grow_to_multiple, grown_extent, outside_mask
from eslam_core.mapping.keyframes import Keyframe, KeyframeStore, select_window
from eslam_core.mapping.mapper import Mapper
from eslam_core.mapping.observed import ObservedSurfaces
from eslam_core.representation.field import SceneField

log = logging.getLogger("eslam")


@dataclass
class MappingStep:
    loss: float
    refined: dict  # keyframe number -> refined (4, 4) float32 pose


def initial_extent(cfg: Config, pf: PreparedFrame, intr: Intrinsics, pose0: np.ndarray) -> np.ndarray:
    """`scene.bound` when given, else the first frame's points with a margin, whole coarse cells per axis."""
    step = cfg.model.coarse_resolution
    if cfg.scene.bound is not None:
        return grow_to_multiple(np.array(cfg.scene.bound, dtype=np.float64), step)
    return estimate_bound(pf.depth.numpy(), intr, pose0, cfg.scene.bound_margin, step)


def surface_points(dirs_cam: torch.Tensor, kf: Keyframe, width: int, stride: int = 2,
                   usable_only: bool = True) -> torch.Tensor:
    """World points of a keyframe's depth (every `stride`-th stored pixel; plenty for 6 cm voxels)."""
    d = kf.depth_image()
    take = torch.zeros_like(kf.usable)
    take[::stride, ::stride] = True
    ok = take & (d > 0) & (kf.usable if usable_only else True)
    flat = torch.nonzero(ok.reshape(-1)).squeeze(1)
    return depth_points_world(dirs_cam[kf.frame_pixels(flat, width)], d.reshape(-1)[flat], kf.pose)


CONSISTENCY_EVERY = 4  # keyframes between two consistency scores of the runtimes' health


@lru_cache(maxsize=4)
def every_second_pixel(height: int, width: int) -> torch.Tensor:
    """(H * W,) bool: the pixels on even rows and columns."""
    take = torch.zeros(height, width, dtype=torch.bool)
    take[::2, ::2] = True
    return take.reshape(-1)


class SceneMap:
    def __init__(self, cfg: Config, intr: Intrinsics, dirs_cam: torch.Tensor):
        self.cfg, self.intr, self.dirs_cam = cfg, intr, dirs_cam
        self.device = resolve_device(cfg.run.device)  # of the field and observed space; keyframes stay on the host
        mc = cfg.mapping
        self.keyframes = KeyframeStore(int(mc.keyframe_budget_mb * 2**20))
        self.mapper = Mapper.of(cfg, dirs_cam, intr.height, intr.width)
        self.rng = np.random.default_rng(cfg.run.seed)
        self.extent: Optional[np.ndarray] = None
        self.field: Optional[SceneField] = None
        # As a submap (submaps/atlas.py): its number and the world pose of its frame, in which its field, extent,
        # observed space and keyframe poses are. None: the world's own frame (one map). Its centre: where the
        # camera was at its first keyframe, in its frame (which submap a keyframe goes to is by distance to it).
        self.number = 0
        self.anchor: Optional[np.ndarray] = None
        self.centre: Optional[np.ndarray] = None
        self.added = 0  # keyframes this map took (a submap's count from its own start, not the keyframes' numbers)
        self.version = 0  # of the field's values: counts the changes (trackers keep what they derive from one)
        self.observed: Optional[ObservedSurfaces] = None
        self.growths = 0
        self.points_outside = 0  # keyframe depth points the map could not cover (outside the bound / max extent)
        self.points_seen = 0
        self._warned_outside = 0.0
        self._consistency_scored_at = -CONSISTENCY_EVERY

    @property
    def started(self) -> bool:
        return self.field is not None

    @property
    def growable(self) -> bool:
        return self.cfg.scene.bound is None

    def start(self, extent: np.ndarray) -> None:
        self.extent = np.asarray(extent, dtype=np.float64)
        self.field = SceneField(self.extent, self.cfg.model, self.device)
        self.version += 1
        self.observed = ObservedSurfaces(self.extent, self.cfg.model.truncation, self.device,
                                         self.cfg.sdf_tracker.observed_after)
        log.info("map: %d parameters (%.1f MB) over %s", self.field.parameter_count(), self.field.nbytes() / 2**20,
                 np.round(self.extent, 3).tolist())

    # ------------------------------------------------------------------------------------------------ keyframes
    def add_keyframe(self, kf: Keyframe) -> None:
        """Take a new keyframe: grow the map to its depth where allowed, mark what stays outside unusable."""
        depth = kf.depth_image().reshape(-1)
        with_depth = flat_nonzero(depth > 0)  # stored pixels with depth, the pixels of `points`
        points = depth_points_world(self.dirs_cam[kf.frame_pixels(with_depth, self.intr.width)], depth[with_depth],
                                    kf.pose)
        outside = outside_mask(points, self.extent)
        if self.growable and outside.any():  # (only the points outside can make the map grow)
            beyond = flat_nonzero(outside)
            self._grow_to(points[beyond], kf.frame_index)
            outside[beyond] = outside_mask(points[beyond], self.extent)
        usable = kf.usable.reshape(-1).clone()
        usable[with_depth[outside]] = False
        kf.usable = usable.reshape(kf.usable.shape)
        self._count_outside(int(outside.sum()), len(points), kf.frame_index)
        inside = flat_nonzero(~outside) if outside.any() else None  # None: all of them
        n_inside = len(points) if inside is None else len(inside)
        drawn = torch.randint(n_inside, (500,)) if n_inside else None
        sample = None if drawn is None else points[drawn if inside is None else inside[drawn]]
        self.keyframes.append(kf, self.intr, sample)
        self.added += 1
        # Observed space takes every 2nd pixel along both axes (as surface_points' default), from the same points.
        on_grid = every_second_pixel(*kf.usable.shape)[with_depth] & usable[with_depth]
        self.observed.add_keyframe(points[on_grid])

    def _grow_to(self, points: torch.Tensor, frame_index: int) -> None:
        sc = self.cfg.scene
        extent, left_out = grown_extent(self.extent, points, self.cfg.model.coarse_resolution, sc.bound_margin,
                                        sc.max_extent)
        if np.array_equal(extent, self.extent):
            return
        if left_out:
            log.warning("frame %d: the map reached scene.max_extent (%.0f m per axis); %d depth points stay outside "
                        "(stray depth? raise scene.max_extent or cut depth with camera.max_depth)", frame_index,
                        sc.max_extent, left_out)
        before, old_bytes = self.extent, self.field.nbytes()
        self.grow(extent)
        log.info("map grown at frame %d: %s -> %s, %d parameters, %.1f -> %.1f MB", frame_index,
                 np.round(before, 2).tolist(), np.round(extent, 2).tolist(), self.field.parameter_count(),
                 old_bytes / 2**20, self.field.nbytes() / 2**20)

    def grow(self, extent: np.ndarray) -> None:
        """A new, larger field over `extent` holding the current features (a new object: see the module docs)."""
        self.extent = np.asarray(extent, dtype=np.float64)
        self.field = self.field.grown(self.extent)
        self.version += 1
        self.observed.grow(self.extent)
        self.growths += 1

    def _count_outside(self, n_out: int, n_valid: int, frame_index: int) -> None:
        self.points_outside += n_out
        self.points_seen += n_valid
        frac = n_out / max(n_valid, 1)
        if frac > 0.05 and frac > 2 * self._warned_outside:
            self._warned_outside = frac
            log.warning("frame %d: %.0f%% of its depth points lie outside the map (%s) and are not mapped (%d so "
                        "far); %s", frame_index, 100 * frac, np.round(self.extent, 2).tolist(), self.points_outside,
                        "enlarge or remove scene.bound in the config" if not self.growable else
                        "raise scene.max_extent")

    def newest_keyframe(self) -> Optional[Keyframe]:
        """The most recent keyframe (a new submap also holds older ones, shared after its first: atlas.py)."""
        return max(self.keyframes, key=lambda kf: kf.number) if len(self.keyframes) else None

    def keyframe_poses(self) -> dict:
        return {kf.number: kf.pose for kf in self.keyframes}

    def set_keyframe_poses(self, poses: dict) -> None:
        for number, pose in poses.items():
            i = self.keyframes.position(int(number))
            if i is not None:
                self.keyframes[i].pose = torch.as_tensor(pose, dtype=torch.float32)

    # -------------------------------------------------------------------------------------------------- mapping
    def warm_up(self, after_iteration: Optional[Callable[[int], object]] = None) -> MappingStep:
        """The first keyframe mapped alone, pose fixed, for `mapping.first_iterations` (paper Sec. 3.4), never cut
        short: `after_iteration` (see Mapper.map) is called for its effects, its answer is not asked."""
        res = self.mapper.map(self.field, self.keyframes, [0], first=True,
                              after_iteration=None if after_iteration is None else
                              lambda done: after_iteration(done) and False)
        self.version += 1
        self.observed.mapped(1)
        return MappingStep(res.loss, {})

    def map_newest(self, after_iteration: Optional[Callable[[int], bool]] = None,
                   iterations: Optional[int] = None) -> MappingStep:
        """One mapping step for the newest keyframe over its window (`iterations`: if not mapping.iterations;
        `after_iteration`: see Mapper.map); refined poses are written back."""
        current = len(self.keyframes) - 1
        kf = self.keyframes[current]
        d = kf.depth_image().reshape(-1)
        with_depth = flat_nonzero(d > 0)
        sample = with_depth[torch.randint(len(with_depth), (min(len(with_depth), 500),))] if len(with_depth) else \
            with_depth
        points = depth_points_world(self.dirs_cam[kf.frame_pixels(sample, self.intr.width)], d[sample], kf.pose)
        window = select_window(self.keyframes, current, points, self.intr, self.cfg.mapping.window, self.rng)
        mc = self.cfg.mapping
        optimise_poses = mc.joint_poses and self.added > mc.joint_poses_after
        res = self.mapper.map(self.field, self.keyframes, window, first=False, optimise_poses=optimise_poses,
                              after_iteration=after_iteration, iterations=iterations)
        self.version += 1
        refined = {}
        for i, pose in res.refined.items():
            self.keyframes[i].pose = pose.float()
            refined[self.keyframes[i].number] = self.keyframes[i].pose
        # (Keyframe numbers count every keyframe made: a submap's own keyframes settle at once. Settled by its own
        # count, a young submap had too little settled space to align to: the generated flat with 2.5 m submaps was
        # lost from frame 623-702 of 1120, none lost before.)
        self.observed.mapped(self.keyframes.made)
        return MappingStep(res.loss, refined)

    def consistency_due(self) -> bool:
        """Whether the runtimes' health should score the consistency again: every CONSISTENCY_EVERY keyframes
        (25-30 ms a score on one core with 70 keyframes, a whole keyframe's tracking; a health figure needs no
        more), and each of a map's first keyframes (few pairs to score, and where a new map goes wrong first)."""
        made = self.keyframes.made
        return made >= 2 and (made <= CONSISTENCY_EVERY or made - self._consistency_scored_at >= CONSISTENCY_EVERY)

    def consistency(self):
        """The depth consistency of the newest keyframe with older ones under the current poses (a
        KeyframeConsistency, mapping/consistency.py): needs no ground truth, so a robot can watch its own drift.
        Reduced keyframes are left out (too coarse to warp)."""
        self._consistency_scored_at = self.keyframes.made
        full = [kf for kf in self.keyframes if kf.stride == 1]
        return keyframe_consistency(_DepthImages(full), [kf.pose for kf in full], self.intr)

    # --------------------------------------------------------------------------------------------- memory, state
    def memory(self) -> dict:
        """Bytes of the map and of the keyframe store (what grows with the explored area / with time)."""
        return {"map_bytes": self.field.nbytes() if self.field is not None else 0,
                "keyframe_bytes": self.keyframes.nbytes(), "keyframes_kept": len(self.keyframes),
                "keyframes_reduced": sum(kf.stride > 1 for kf in self.keyframes),
                "keyframes_dropped": self.keyframes.dropped, "map_growths": self.growths}

    def state_dict(self) -> dict:
        return {
            "extent": None if self.extent is None else torch.from_numpy(self.extent),
            "field": {k: v.cpu() for k, v in self.field.state_dict().items()} if self.field is not None else None,
            "keyframes": [dict(kf.__dict__) for kf in self.keyframes],
            "keyframes_made": self.keyframes.made,
            "keyframes_added": self.added,
            "points_outside": self.points_outside,
            "points_seen": self.points_seen,
            "rng": self.rng.bit_generator.state,
            "counts": {"map_growths": self.growths, "keyframes_dropped": self.keyframes.dropped},
        }

    def load_state_dict(self, state: dict) -> None:
        if state["field"] is not None:
            self.start(state["extent"].numpy())
            self.field.load_state_dict(state["field"])
            self.version += 1
        self.keyframes.replace_all([Keyframe(**kf) for kf in state["keyframes"]])
        self.keyframes.made = max(self.keyframes.made, state["keyframes_made"])
        self.added = state.get("keyframes_added", self.keyframes.made)
        if self.observed is not None:
            for kf in self.keyframes:
                self.observed.add_keyframe(surface_points(self.dirs_cam, kf, self.intr.width))
            self.observed.settle_all()
        self.points_outside, self.points_seen = state["points_outside"], state["points_seen"]
        self.rng.bit_generator.state = state["rng"]
        counts = state.get("counts", {})  # (checkpoints of version 3 written before the counts were kept)
        self.growths = counts.get("map_growths", 0)
        self.keyframes.dropped = counts.get("keyframes_dropped", 0)


class _DepthImages:
    """The keyframes' depth images in metres, each decoded once when first read (consistency reads the newest one
    for every pair it tries, and a few of the others)."""

    def __init__(self, keyframes: list[Keyframe]) -> None:
        self.keyframes = keyframes
        self._decoded: dict[int, torch.Tensor] = {}

    def __len__(self) -> int:
        return len(self.keyframes)

    def __getitem__(self, i: int) -> torch.Tensor:
        if i not in self._decoded:
            self._decoded[i] = self.keyframes[i].depth_image()
        return self._decoded[i]
