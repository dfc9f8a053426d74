"""Submaps (not part of the paper's method): the scene as several local maps, each a SceneMap in its own frame, and
a pose graph over their frames that loop closure corrects.

A submap's frame is the world's moved to where the camera was when it began (its *anchor*, a world pose; the
first submap's is the world's own frame): its feature planes, extent, observed space and keyframe poses are in that
frame, so moving the anchor moves the submap rigidly, without refitting a plane. Its planes stay axis-aligned and
bounded (a few metres), and two storeys land in different submaps instead of sharing every xy projection.

Which submap a keyframe goes to: the active one while the camera stays within `submaps.radius_m` of its centre
(where the camera was at its first keyframe); else the nearest other submap whose centre is within that distance
(the camera came back); else a new submap anchored at the camera's position (the world's axes kept), which shares
the newest keyframes of the one left (`overlap`). Tracking and mapping work on the active submap.

The pose graph (pose_graph.py) has a node per submap anchor. Starting submap j from submap i adds an odometry edge,
the relative pose of the anchors as tracked, weighted by the drift allowed over the distance between them
(`submaps.drift_m_per_m`, `drift_deg_per_m`). A loop edge comes from a keyframe of submap j placed by the features
of a keyframe of submap i (the map check's PnP, map_check.py): the keyframe's pose in i's frame and in j's give
the relative pose of the anchors as that place sees it. The graph is solved (GNC refuses a loop that disagrees with
the rest), every anchor moves to its solution, and every keyframe of a moved submap with it: those are the pose
corrections that the trajectory, relocalization and the outputs follow (TrackingSession.apply).
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from typing import Optional

import numpy as np
import torch

from eslam_core.camera import Intrinsics
from eslam_core.config import Config
from eslam_core.mapping.extent import estimate_bound
from eslam_core.mapping.keyframes import Keyframe
from eslam_core.mapping.scene_map import SceneMap
from eslam_core.submaps.pose_graph import PoseGraph
from eslam_core.tracking.map_check import MapCheck

log = logging.getLogger("eslam")

# The accuracy of a keyframe placed by another's features (PnP refined with depth; relocalization.py): on the
# development data within 1-3 cm and 1-2 degrees of the tracked pose where the map agrees with itself.
LOOP_SIGMA_M, LOOP_SIGMA_DEG = 0.03, 2.0
# The keyframes a new submap shares with the one the camera leaves (Atlas.overlap).
OVERLAP_KEYFRAMES = 3


@dataclass(frozen=True)
class LoopClosure:
    """A loop the graph kept: keyframe `keyframe` (made at frame `revisit`) placed by keyframe `by` of another
    submap, `metres` / `degrees` from where it was tracked; the map corrected at frame `corrected`, `seconds` of
    input after the revisit (frame stamps)."""
    keyframe: int
    by: int
    metres: float
    degrees: float
    revisit: int
    corrected: int
    seconds: float = float("nan")


def information(sigma_m: float, sigma_deg: float) -> np.ndarray:
    """A pose graph edge's information for independent standard deviations (rotation first, gtsam's order)."""
    return np.diag([np.radians(sigma_deg) ** -2] * 3 + [sigma_m ** -2] * 3)


def anchored_at(pose: np.ndarray) -> np.ndarray:
    """A submap's anchor at a camera pose: the camera's position, the world's axes (the planes stay aligned with
    the floor and walls that squared the map frame, map_frame.py)."""
    anchor = np.eye(4)
    anchor[:3, 3] = np.asarray(pose, dtype=np.float64)[:3, 3]
    return anchor


class Atlas:
    def __init__(self, cfg: Config, intr: Intrinsics, dirs_cam: torch.Tensor):
        self.cfg, self.intr, self.dirs_cam = cfg, intr, dirs_cam
        self.submaps: list[SceneMap] = []
        self.active: Optional[SceneMap] = None
        self.owner: dict[int, int] = {}  # keyframe number -> its submap's number
        self.graph = PoseGraph()
        self.loops = 0  # loop edges the graph kept
        self.closures: list[LoopClosure] = []  # each loop as it was closed (a later solve may refuse it)

    @property
    def started(self) -> bool:
        return self.active is not None

    def new_submap(self, anchor: Optional[np.ndarray]) -> SceneMap:
        """An empty submap with that anchor (None: the world's frame), made the active one."""
        sub = SceneMap(self.cfg, self.intr, self.dirs_cam)
        sub.number, sub.anchor = len(self.submaps), anchor
        self.graph.add_node(sub.number, np.eye(4) if anchor is None else anchor)
        if self.active is not None:  # the anchors' relative pose as tracked, within the drift over the distance
            before = self.anchor(self.active)
            distance = float(np.linalg.norm(self.anchor(sub)[:3, 3] - self.centre(self.active)))
            sc = self.cfg.submaps
            self.graph.add_edge(self.active.number, sub.number, np.linalg.inv(before) @ self.anchor(sub),
                                information(max(sc.drift_m_per_m * distance, 0.01),
                                            max(sc.drift_deg_per_m * distance, 0.5)), loop=False)
        self.submaps.append(sub)
        self.active = sub
        return sub

    @staticmethod
    def anchor(sub: SceneMap) -> np.ndarray:
        return np.eye(4) if sub.anchor is None else sub.anchor

    def centre(self, sub: SceneMap) -> np.ndarray:
        """Where the camera was at the submap's first keyframe, in the world."""
        A = self.anchor(sub)
        return A[:3, :3] @ sub.centre + A[:3, 3]

    def local(self, sub: SceneMap, kf: Keyframe) -> Keyframe:
        """The keyframe as its submap keeps it: its pose in the submap's frame (the images are shared)."""
        self.owner[kf.number] = sub.number
        local = kf if sub.anchor is None else kf.moved(np.linalg.inv(sub.anchor))
        if sub.centre is None:
            sub.centre = local.pose.double().numpy()[:3, 3].copy()
        return local

    def owns(self, sub: SceneMap, number: int) -> bool:
        """Whether the keyframe is the submap's own (not one it shares from the submap before it: `overlap`)."""
        return self.owner.get(int(number)) == sub.number

    def to_world(self, sub: SceneMap, poses: dict) -> dict:
        """Keyframe number -> world pose, of the submap's own keyframes' poses in its frame (a shared keyframe's
        pose is its owner's to say)."""
        A = self.anchor(sub)
        return {n: torch.from_numpy(A @ torch.as_tensor(p).double().numpy()).float()
                for n, p in poses.items() if self.owns(sub, n)}

    def to_world_keyframes(self, sub: SceneMap) -> list[Keyframe]:
        """A submap's own keyframes with world poses (the images shared): what relocalization indexes."""
        return [kf.moved(self.anchor(sub)) for kf in sub.keyframes if self.owns(sub, kf.number)]

    def world_keyframes(self) -> list[Keyframe]:
        """Every submap's own keyframes with world poses (a loaded map's, to relocalize against)."""
        return [kf for sub in self.submaps for kf in self.to_world_keyframes(sub)]

    def overlap(self, previous: SceneMap, sub: SceneMap) -> list[Keyframe]:
        """The newest OVERLAP_KEYFRAMES keyframes of the submap the camera leaves, in the new one's frame: a new
        submap mapped from its first keyframe alone tracked worse than the map it left (long room, 1 m submaps: ATE
        1.2 cm against 0.8 for one map); shared, they map the new submap's first views from the same places."""
        to_new = np.linalg.inv(self.anchor(sub)) @ self.anchor(previous)
        newest = sorted((kf for kf in previous.keyframes if kf.stride == 1), key=lambda kf: kf.number)
        return [kf.moved(to_new) for kf in newest[-OVERLAP_KEYFRAMES:]]

    def submap_for(self, kf: Keyframe) -> Optional[SceneMap]:
        """Where a new keyframe goes: the active submap while the camera is within `submaps.radius_m` of its
        centre, else the nearest other one within it (made active); None: a new submap is due there."""
        radius = self.cfg.submaps.radius_m
        position = kf.pose.double().numpy()[:3, 3]
        if radius <= 0 or np.linalg.norm(position - self.centre(self.active)) <= radius:
            return self.active
        distances = [np.linalg.norm(position - self.centre(s)) for s in self.submaps]
        nearest = int(np.argmin(distances))
        if distances[nearest] > radius:
            return None
        if self.submaps[nearest] is not self.active:
            log.info("keyframe %d: back in submap %d (%.1f m from its centre)", kf.number, nearest,
                     distances[nearest])
            self.active = self.submaps[nearest]
        return self.active

    def place(self, kf: Keyframe) -> tuple[SceneMap, bool]:
        """A new keyframe (world pose) into its submap (`submap_for`), or into a new submap begun there, over the
        keyframe's own view and sharing the newest keyframes of the one left (`overlap`). Returns the submap and
        whether it began with this keyframe (to be warmed up as the first map was)."""
        sub = self.submap_for(kf)
        if sub is not None:
            sub.add_keyframe(self.local(sub, kf))
            return sub, False
        previous = self.active
        sub = self.new_submap(anchored_at(kf.pose.double().numpy()))
        local = self.local(sub, kf)
        sub.start(estimate_bound(local.depth_image().numpy(), self.intr, local.pose.double().numpy(),
                                 self.cfg.scene.bound_margin, self.cfg.model.coarse_resolution))
        sub.add_keyframe(local)
        for shared in self.overlap(previous, sub):
            sub.add_keyframe(shared)
        log.info("keyframe %d: submap %d begins (%d submaps)", kf.number, sub.number, len(self.submaps))
        return sub, True

    def follow(self, position: np.ndarray, found_by: Optional[int] = None) -> SceneMap:
        """The submap to track a camera at `position` (world) against when it makes no keyframe (localization): the
        submap of the keyframe whose features found it (`found_by`, a relocalization), else the one whose centre
        is nearest, once nearer than the active one's by a quarter of `submaps.radius_m` (no flapping at a
        border). Made active, returned."""
        if len(self.submaps) < 2:  # (a one-map checkpoint's submap has no centre: nothing to follow)
            return self.active
        if found_by is not None and found_by in self.owner:
            chosen = self.submaps[self.owner[found_by]]
        else:
            distances = [np.linalg.norm(position - self.centre(s)) for s in self.submaps]
            nearest = int(np.argmin(distances))
            own = distances[self.active.number]
            chosen = self.submaps[nearest] if own - distances[nearest] > 0.25 * self.cfg.submaps.radius_m \
                else self.active
        if chosen is not self.active:
            log.info("the camera is in submap %d now", chosen.number)
            self.active = chosen
        return chosen

    # ---------------------------------------------------------------------------------------------- loops
    def keyframe_pose(self, number: int) -> Optional[np.ndarray]:
        """A kept keyframe's world pose (None: not kept)."""
        sub = self.submaps[self.owner[number]] if number in self.owner else None
        i = None if sub is None else sub.keyframes.position(number)
        return None if i is None else self.anchor(sub) @ sub.keyframes[i].pose.double().numpy()

    def close_loop(self, check: MapCheck, frame: int = -1, stamp: float = float("nan")) -> dict:
        """A keyframe placed by another submap's keyframe (`check`) as a loop edge: the graph solved and the
        submaps moved, at frame `frame` (stamped `stamp`). Returns the corrections (keyframe number -> world pose),
        empty where the check is no loop (the same submap) or the graph refused it."""
        if not self.cfg.submaps.loop_closure or check.placed is None:
            return {}
        i, j = self.owner.get(check.by), self.owner.get(check.keyframe)
        tracked = self.keyframe_pose(check.keyframe)
        if i is None or j is None or i == j or tracked is None:
            return {}
        A_i, A_j = self.anchor(self.submaps[i]), self.anchor(self.submaps[j])
        in_i = np.linalg.inv(A_i) @ check.placed  # the keyframe in i's frame, as i's keyframe places it
        in_j = np.linalg.inv(A_j) @ tracked  # and in j's, as tracked and mapped
        self.graph.add_edge(i, j, in_i @ np.linalg.inv(in_j), information(LOOP_SIGMA_M, LOOP_SIGMA_DEG), loop=True)
        solution = self.graph.solve()
        if len(self.graph.edges) - 1 in solution.rejected:
            log.info("keyframe %d placed by keyframe %d (submaps %d, %d): refused as a loop (it disagrees with the "
                     "graph)", check.keyframe, check.by, j, i)
            return {}
        self.loops = sum(e.loop for e in self.graph.edges) - len(solution.rejected)
        kf = self.submaps[j].keyframes[self.submaps[j].keyframes.position(check.keyframe)]
        self.closures.append(LoopClosure(int(check.keyframe), int(check.by), float(check.metres),
                                         float(check.degrees), int(kf.frame_index), int(frame),
                                         float(stamp) - float(kf.timestamp)))
        self.graph.initial.update(solution.poses)  # (the next solve starts from here)
        corrections = {}
        for sub in self.submaps:
            new = solution.poses[sub.number]
            if np.allclose(new, self.anchor(sub), atol=1e-6):
                continue
            sub.anchor = new
            corrections.update(self.to_world(sub, sub.keyframe_poses()))
        log.info("loop closed: keyframe %d of submap %d placed by keyframe %d of submap %d; %d submaps moved",
                 check.keyframe, j, check.by, i, len({self.owner[n] for n in corrections}))
        return corrections

    # ----------------------------------------------------------------------------------------- state, memory
    def memory(self) -> dict:
        out: dict = {}
        for sub in self.submaps:
            for key, value in sub.memory().items():
                out[key] = out.get(key, 0) + value
        return {**out, "submaps": len(self.submaps), "loops_closed": self.loops}

    def state_dict(self) -> dict:
        return {"submaps": [{"number": s.number, "anchor": None if s.anchor is None else torch.from_numpy(s.anchor),
                             "centre": torch.from_numpy(s.centre), "map": s.state_dict()} for s in self.submaps],
                "active": None if self.active is None else self.active.number,
                "owner": dict(self.owner),
                "edges": [{"a": e.a, "b": e.b, "T_ab": torch.from_numpy(e.T_ab),
                           "information": torch.from_numpy(e.information), "loop": e.loop}
                          for e in self.graph.edges],
                "loops": self.loops, "closures": [asdict(c) for c in self.closures]}

    def load_single_map(self, state: dict) -> None:
        """A checkpoint of one map (no submaps): it is the first submap, every keyframe its own."""
        self.active.load_state_dict(state)
        self.owner = {kf.number: self.active.number for kf in self.active.keyframes}

    def load_state_dict(self, state: dict) -> None:
        for saved in state["submaps"]:
            anchor = None if saved["anchor"] is None else saved["anchor"].numpy()
            sub = SceneMap(self.cfg, self.intr, self.dirs_cam)
            sub.number, sub.anchor, sub.centre = saved["number"], anchor, saved["centre"].numpy()
            sub.load_state_dict(saved["map"])
            self.graph.add_node(sub.number, self.anchor(sub))
            self.submaps.append(sub)
        for e in state["edges"]:
            self.graph.add_edge(e["a"], e["b"], e["T_ab"].numpy(), e["information"].numpy(), e["loop"])
        self.owner = {int(k): int(v) for k, v in state["owner"].items()}
        self.loops = int(state.get("loops", 0))
        self.closures = [LoopClosure(**c) for c in state.get("closures", [])]
        self.active = None if state["active"] is None else self.submaps[state["active"]]
