"""Relocalization: find the camera again from the stored keyframes after tracking was lost.

Two steps, as in PTAM and ORB-SLAM:
1. Place recognition ranks the keyframes by how much the frame looks like them, with two compact global
   descriptors: PTAM's small blurry image (the grey image shrunk to 40 pixels wide, blurred, zero mean, compared
   by normalised cross-correlation) and a bag of binary words (each ORB descriptor quantised to its nearest word of
   a vocabulary clustered from the keyframes' own descriptors, TF-IDF weighted, compared by cosine). The thumbnail
   recognises views seen from nearly the same place; the words survive larger viewpoint changes.
2. A geometric check verifies the best candidates: the frame's ORB features are matched to the keyframe's, whose
   depth back-projects them into the world; PnP RANSAC (cv2.solvePnPRansac) gives a camera pose and its inliers.
   The pose is then refined on the reprojection errors together with the frame's own measured depths (PnP alone
   confuses a turn with a sideways step when the points lie at similar depths, e.g. one wall), and kept if enough
   matches are inliers of it both in the image and in depth.

The pose is a starting point: the normal tracker refines it against the map afterwards. Measured (bench/
relocalize.py): ICL office, 100 % of the queries within 5 cm / 5 deg, median error 0.4 cm; the synthetic room's
tests, views 15 cm / 8 deg off the keyframes' path found to 2 cm / 0.5 deg.
A database is not thread-safe: guard it with a lock if keyframes are added while another thread queries it.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from typing import Generator, Optional

import cv2
import numpy as np
import torch
from scipy.optimize import least_squares

from eslam_core.camera import Intrinsics
from eslam_core.config import RelocalizationConfig
from eslam_core.geometry import depth_points_world, pixel_directions

DATABASE_VERSION = 1
DESCRIPTOR_BYTES = 32  # ORB: 256 binary tests


class RelocalizationError(ValueError):
    pass


Steps = Generator[None, None, Optional["Relocalization"]]  # work done one step per `next`; returns a place


def run_to_end(steps: Generator):
    """Every step of a generator of work; its return value."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value


@dataclass
class Relocalization:
    pose: np.ndarray  # (4, 4) float64 camera-to-world
    keyframe_id: int  # the keyframe whose features gave the pose
    inliers: int  # matches the pose reprojects within the threshold and, where measured, at the measured depth
    matches: int  # features matched to the keyframe (inliers / matches is the inlier ratio)
    depth_agreement: float  # of the reprojected matches with measured depth, the fraction at that depth
    seconds: float  # time the query took, all candidates included

    @property
    def inlier_ratio(self) -> float:
        return self.inliers / max(self.matches, 1)


# ------------------------------------------------------------------------------------------------ image features

def grey_image(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise RelocalizationError(f"colour must be an H x W x 3 uint8 RGB image, got {rgb.dtype} {rgb.shape}")
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


# ORB's 31-pixel patch keeps its keypoints 31 pixels from the border: on a 160 x 120 image that leaves 98 x 58 of
# it, and on the generated corridor's return (datasets/degenerate.py) no frame of 15 was relocalized; searched at
# twice the size, 7 of 15 were, within 0.2-2.4 cm. Narrower images are searched at a multiple of their size.
ORB_MIN_WIDTH = 320


def orb_features(grey: np.ndarray, n: int, fast_threshold: int = 20,
                 fast_threshold_min: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """Keypoint positions (N, 2) float32 (u, v) and descriptors (N, 32) uint8."""
    scale = max(1, math.ceil(ORB_MIN_WIDTH / grey.shape[1]))
    if scale > 1:
        grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_LINEAR)
    keypoints, descriptors = cv2.ORB_create(nfeatures=n, fastThreshold=fast_threshold).detectAndCompute(grey, None)
    if len(keypoints) < n // 2 and fast_threshold_min < fast_threshold:
        keypoints, descriptors = cv2.ORB_create(nfeatures=n, fastThreshold=fast_threshold_min).detectAndCompute(
            grey, None)
    if descriptors is None:
        return np.zeros((0, 2), np.float32), np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
    # (The centre of upsampled pixel i lies at (i + 0.5) / scale - 0.5 in the original image.)
    uv = (np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2) + 0.5) / scale - 0.5
    return uv.astype(np.float32), descriptors


def thumbnail(grey: np.ndarray, width: int, blur: float) -> np.ndarray:
    """PTAM's small blurry image: zero mean, unit norm, so that a dot product is the normalised cross-correlation
    (0 for a uniform image such as a covered lens)."""
    h, w = grey.shape
    small = cv2.resize(grey, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA).astype(np.float32)
    if blur > 0:
        small = cv2.GaussianBlur(small, (0, 0), blur)
    small = (small - small.mean()).reshape(-1)
    norm = float(np.linalg.norm(small))
    return small / norm if norm > 1e-3 * small.size else np.zeros_like(small)


def depth_at(depth: np.ndarray, uv: np.ndarray, edge: float) -> np.ndarray:
    """Depth at the nearest pixel of each keypoint, 0 where missing or where the 3x3 neighbourhood spans a depth
    discontinuity (corners often sit on object outlines, where the pixel may belong to either side)."""
    h, w = depth.shape
    u = np.clip(np.rint(uv[:, 0]).astype(np.int64), 1, w - 2)
    v = np.clip(np.rint(uv[:, 1]).astype(np.int64), 1, h - 2)
    patches = np.stack([depth[v + dv, u + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], axis=1)
    z = depth[v, u].astype(np.float64)
    spread = patches.max(1) - patches.min(1)
    ok = (patches.min(1) > 0) & (spread <= edge * z)
    return np.where(ok, z, 0.0)


def camera_points(uv: np.ndarray, z: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Camera-frame points (N, 3) of keypoints at planar depths z."""
    u, v = torch.from_numpy(uv[:, 0].astype(np.float64)), torch.from_numpy(uv[:, 1].astype(np.float64))
    dirs = pixel_directions(u, v, intr.fx, intr.fy, intr.cx, intr.cy)
    return depth_points_world(dirs, torch.from_numpy(z), torch.eye(4, dtype=torch.float64)).numpy()


# ------------------------------------------------------------------------------------------------ pose

def project(world: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) and depths (N,) of world points seen by the world-to-camera pose (rvec, tvec), with OpenCV's
    projection (the one solvePnP minimises)."""
    R = cv2.Rodrigues(rvec)[0]
    z = world @ R[2] + float(np.ravel(tvec)[2])
    pixels, _ = cv2.projectPoints(world, rvec, tvec, intr.matrix(), None)
    return pixels.reshape(-1, 2), z


def refine_with_depth(world: np.ndarray, pixels: np.ndarray, depth: np.ndarray, depth_sigma: np.ndarray,
                      rvec: np.ndarray, tvec: np.ndarray, intr: Intrinsics,
                      pixel_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """The world-to-camera pose minimising the reprojection errors and, where the frame measured depth (> 0), the
    depth errors, each in units of its noise (pixels; `depth_sigma` metres per point), with Huber's loss.

    PnP alone leaves an ambiguity when the points lie at similar depths: turning the camera while moving it
    sideways (a rotation about a point in the scene) shifts the image little. The points' depths then change by
    several percent, which the frame's own depth measures."""
    has = depth > 0

    def residuals(x: np.ndarray) -> np.ndarray:
        proj, z = project(world, x[:3], x[3:], intr)
        return np.concatenate([((proj - pixels) / pixel_sigma).ravel(),
                               (z[has] - depth[has]) / depth_sigma[has]])

    def jacobian(x: np.ndarray) -> np.ndarray:
        # (Analytic: finite differences took 7 projections per step, two thirds of a map check's time.)
        _, d_pixels = cv2.projectPoints(world, x[:3], x[3:], intr.matrix(), None)  # rows u0 v0 u1 ...; rvec, tvec
        d_rotation = cv2.Rodrigues(x[:3])[1]  # (3, 9): d R.ravel() / d rvec
        d_z = np.zeros((int(has.sum()), 6))
        d_z[:, :3] = world[has] @ d_rotation[:, 6:9].T  # z = R[2] . X + t_z
        d_z[:, 5] = 1.0
        return np.vstack([d_pixels[:, :6] / pixel_sigma, d_z / depth_sigma[has, None]])

    x0 = np.concatenate([np.ravel(rvec), np.ravel(tvec)]).astype(np.float64)
    fit = least_squares(residuals, x0, jac=jacobian, loss="huber", f_scale=2.0, max_nfev=50, x_scale="jac")
    return fit.x[:3].reshape(3, 1), fit.x[3:].reshape(3, 1)


# ------------------------------------------------------------------------------------------------ bag of words

def hamming_nearest(queries: np.ndarray, train: np.ndarray) -> np.ndarray:
    """Index of the nearest train descriptor of each query descriptor."""
    if len(queries) == 0 or len(train) == 0:
        return np.zeros(0, np.int64)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING).match(queries, train)
    return np.array([m.trainIdx for m in matches], np.int64)


def binary_vocabulary(descriptors: np.ndarray, words: int, rng: np.random.Generator,
                      iterations: int = 3) -> np.ndarray:
    """k-majority clustering of binary descriptors (k-means with Hamming distance and bitwise-majority centres)."""
    words = min(words, len(descriptors))
    centres = descriptors[rng.choice(len(descriptors), words, replace=False)].copy()
    bits = np.unpackbits(descriptors, axis=1)
    for _ in range(iterations):
        nearest = hamming_nearest(descriptors, centres)
        counts = np.bincount(nearest, minlength=words)
        # The set bits of each word's descriptors, counted in one bincount (np.add.at took 3x as long).
        slots = (nearest[:, None] * bits.shape[1] + np.arange(bits.shape[1]))[bits.astype(bool)]
        votes = np.bincount(slots, minlength=words * bits.shape[1]).reshape(words, bits.shape[1])
        filled = counts > 0
        centres[filled] = np.packbits(2 * votes[filled] > counts[filled, None], axis=1)
    return centres


def term_counts(word_ids: np.ndarray, words: int) -> np.ndarray:
    """How often each of the vocabulary's `words` occurs in a bag of words."""
    return np.bincount(word_ids, minlength=words).astype(np.float64)


def tf_idf(counts: np.ndarray, idf: np.ndarray) -> np.ndarray:
    """TF-IDF vectors of term counts (..., words), each of unit length."""
    v = counts * idf
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > 0)


# ------------------------------------------------------------------------------------------------ database

NEARBY_VIEW_DEG = 45.0  # a keyframe near the camera that looks within this of its way sees much of what it sees


@dataclass
class KeyframeEntry:
    """A keyframe as the index stores it (a pickle of it is what the mapping process sends the tracker's replica)."""
    keyframe_id: int
    keypoints: np.ndarray  # (N, 2) float32, features with usable depth only
    descriptors: np.ndarray  # (N, 32) uint8
    points_cam: np.ndarray  # (N, 3) float64, the keypoints back-projected in the keyframe's camera
    thumbnail: np.ndarray  # (h * w,) float32
    pose: np.ndarray  # (4, 4) float64 camera-to-world
    words: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # word of each descriptor


@dataclass
class _Query:
    keypoints: np.ndarray
    descriptors: np.ndarray
    depth: np.ndarray  # (N,) measured depth at each keypoint, 0 = none
    thumbnail: np.ndarray
    term_counts: Optional[np.ndarray] = None  # its bag of words, where known (a stored keyframe's)


class KeyframeDatabase:
    """Keyframes stored for relocalization: their ORB features with depth, thumbnail and pose."""

    def __init__(self, cfg: Optional[RelocalizationConfig] = None, seed: int = 0):
        self.cfg = cfg or RelocalizationConfig()
        self.entries: dict[int, KeyframeEntry] = {}
        self.seed = seed
        self._vocabulary: Optional[np.ndarray] = None
        self._vocabulary_from = 0  # descriptors in the database when the vocabulary was built
        # The bag of words, kept up to date one keyframe at a time (a revisit's keyframes come and go for hours:
        # recounting every keyframe's words on each made indexing slower as the store filled).
        self._term_counts: dict[int, np.ndarray] = {}  # per keyframe, as words are counted (term_counts)
        self._documents: Optional[np.ndarray] = None  # (words,) keyframes in which each word occurs
        self._descriptors = 0  # in all entries

    def __len__(self) -> int:
        return len(self.entries)

    # -------------------------------------------------------------------------------------------- building
    def add(self, keyframe_id: int, rgb: np.ndarray, depth: np.ndarray, pose, intr: Intrinsics) -> int:
        """Store a keyframe (a new id, or replacing one); returns the number of features with depth kept."""
        grey = grey_image(rgb)
        depth = _checked_depth(depth, grey.shape, intr)
        uv, desc = orb_features(grey, self.cfg.features, self.cfg.fast_threshold, self.cfg.fast_threshold_min)
        z = depth_at(depth, uv, self.cfg.edge_tolerance) if len(uv) else np.zeros(0)
        keep = z > 0
        entry = KeyframeEntry(int(keyframe_id), uv[keep], desc[keep], camera_points(uv[keep], z[keep], intr),
                       thumbnail(grey, self.cfg.thumbnail_width, self.cfg.thumbnail_blur), _pose64(pose))
        self._insert(entry)
        return len(entry.keypoints)

    def set_pose(self, keyframe_id: int, pose) -> None:
        """Mapping refined the keyframe's pose: its features move with it."""
        self.entries[int(keyframe_id)].pose = _pose64(pose)

    def remove(self, keyframe_id: int) -> None:
        """Forget a keyframe (e.g. one the keyframe budget dropped)."""
        entry = self.entries.pop(int(keyframe_id), None)
        if entry is None:
            return
        self._descriptors -= len(entry.descriptors)
        counts = self._term_counts.pop(entry.keyframe_id, None)
        if counts is not None:
            self._documents -= counts > 0

    def insert(self, entry: KeyframeEntry) -> None:
        """A keyframe indexed elsewhere (its features extracted by another database's `add`)."""
        self._insert(entry)

    def _insert(self, entry: KeyframeEntry) -> None:
        self.remove(entry.keyframe_id)
        self.entries[entry.keyframe_id] = entry
        self._descriptors += len(entry.descriptors)
        if self._vocabulary is not None:
            self._count_words(entry)

    def _count_words(self, entry: KeyframeEntry) -> None:
        entry.words = hamming_nearest(entry.descriptors, self._vocabulary)
        counts = term_counts(entry.words, len(self._vocabulary))
        self._term_counts[entry.keyframe_id] = counts
        self._documents += counts > 0

    def build_vocabulary(self) -> None:
        """(Re)build the vocabulary from the keyframes' descriptors if they have doubled since the last build: the
        words then fit the scene, and the cost stays amortised over the keyframes added. The first query does it
        when needed; call it beforehand (e.g. after loading a map) to keep that cost off the first lost frame."""
        total = self._descriptors
        if total == 0 or (self._vocabulary is not None and total < 2 * self._vocabulary_from):
            return
        rng = np.random.default_rng(self.seed)
        descriptors = np.concatenate([e.descriptors for e in self.entries.values()])
        words = max(16, min(self.cfg.words, total // 20))
        if len(descriptors) > 10 * words:  # 10 per word place the words about as well as all of them
            descriptors = descriptors[rng.choice(len(descriptors), 10 * words, replace=False)]
        self._vocabulary = binary_vocabulary(descriptors, words, rng)
        self._vocabulary_from = total
        self._recount_words()

    def _recount_words(self) -> None:
        self._term_counts, self._documents = {}, np.zeros(len(self._vocabulary), np.int64)
        for e in self.entries.values():
            self._count_words(e)

    def _idf(self) -> np.ndarray:
        """Inverse document frequency of each word over the keyframes."""
        return np.log((len(self.entries) + 1) / (self._documents + 1))

    # -------------------------------------------------------------------------------------------- querying
    def relocalize(self, rgb: np.ndarray, depth: np.ndarray, intr: Intrinsics) -> Optional[Relocalization]:
        """The camera pose of a frame from the stored keyframes, or None if no keyframe explains it."""
        start = time.perf_counter()
        if not self.entries:
            return None
        grey = grey_image(rgb)
        depth = _checked_depth(depth, grey.shape, intr)
        uv, desc = orb_features(grey, self.cfg.features, self.cfg.fast_threshold, self.cfg.fast_threshold_min)
        if len(uv) < self.cfg.min_inliers:
            return None  # a covered lens, a blank wall: nothing to match
        query = _Query(uv, desc, depth_at(depth, uv, self.cfg.edge_tolerance),
                       thumbnail(grey, self.cfg.thumbnail_width, self.cfg.thumbnail_blur))
        best = self._best(query, self.candidates(query), intr)
        if best is not None:
            best.seconds = time.perf_counter() - start
        return best

    def place(self, keyframe_id: int, intr: Intrinsics, older_than: int) -> Optional[Relocalization]:
        """Where the features of the keyframes numbered below `older_than` place a stored keyframe (by its own
        stored features), or None if none of them explains it: the map checked against itself."""
        return run_to_end(self.placing(keyframe_id, intr, older_than))

    def placing(self, keyframe_id: int, intr: Intrinsics, older_than: int) -> Steps:
        """`place` one candidate at a time, for a caller that works in slots of idle time: each step verifies one
        (a few milliseconds; all of a keyframe's candidates took up to 45 ms on 7-Scenes, and a live tracker that
        spent them at once dropped the frames that came meanwhile). The generator returns the place."""
        entry = self.entries[int(keyframe_id)]
        older = [i for i in self.entries if i < older_than]
        if not older or len(entry.descriptors) < self.cfg.min_inliers:
            return None
        self.build_vocabulary()
        query = self.query_of(keyframe_id)
        candidates = list(dict.fromkeys(self.nearby(entry.pose, older) + self.candidates(query, older)))
        return (yield from self._best_steps(query, candidates, intr))

    def query_of(self, keyframe_id: int) -> _Query:
        """A stored keyframe as a query (its own features, thumbnail and words)."""
        entry = self.entries[int(keyframe_id)]
        return _Query(entry.keypoints, entry.descriptors, entry.points_cam[:, 2], entry.thumbnail,
                      self._term_counts.get(entry.keyframe_id))

    def nearby(self, pose: np.ndarray, among: list[int]) -> list[int]:
        """The `candidates` keyframes of `among` nearest to `pose` (4x4) that look the same way (optical axes within
        NEARBY_VIEW_DEG) and lie within `max_jump_m`, nearest first: where a keyframe made on the camera's return
        should find the place it returns to. Appearance alone ranks look-alike places first where the scene repeats
        itself (the generated corridor loop's furniture: on the return to where the walk began, none of the first
        keyframes was among the best three of either ranking, and no loop was found)."""
        same_way = math.cos(math.radians(NEARBY_VIEW_DEG))
        near = []
        for i in among:
            other = self.entries[i].pose
            metres = float(np.linalg.norm(other[:3, 3] - pose[:3, 3]))
            if metres <= self.cfg.max_jump_m and other[:3, 2] @ pose[:3, 2] >= same_way:
                near.append((metres, i))
        return [i for _, i in sorted(near)[:self.cfg.candidates]]

    def _best(self, query: _Query, candidates: list[int], intr: Intrinsics) -> Optional[Relocalization]:
        """The candidate keyframe giving the most inliers, verified in order until one gives `enough_inliers`."""
        return run_to_end(self._best_steps(query, candidates, intr))

    def _best_steps(self, query: _Query, candidates: list[int], intr: Intrinsics) -> Steps:
        best: Optional[Relocalization] = None
        for n, keyframe_id in enumerate(candidates):
            if n:
                yield
            entry = self.entries.get(keyframe_id)  # (a step may come after the keyframe was forgotten)
            found = None if entry is None else self._verify(query, entry, intr)
            if found is not None and (best is None or found.inliers > best.inliers):
                best = found
                if best.inliers >= self.cfg.enough_inliers:
                    break
        return best

    def candidates(self, query: _Query, among: Optional[list[int]] = None) -> list[int]:
        """The keyframes (of `among`, default all) most like the frame, in the order they are verified: the best
        `candidates` of each ranking, alternating between the two (thumbnail first), without repeats."""
        ids = list(self.entries) if among is None else among
        k, how = self.cfg.candidates, self.cfg.retrieval
        rankings = []
        if how in ("both", "thumbnail"):
            by_thumbnail = np.array([float(self.entries[i].thumbnail @ query.thumbnail) for i in ids])
            rankings.append([ids[j] for j in np.argsort(-by_thumbnail, kind="stable")[:k]])
        if how in ("both", "words"):
            self.build_vocabulary()
            idf = self._idf()
            counts = query.term_counts if query.term_counts is not None else \
                term_counts(hamming_nearest(query.descriptors, self._vocabulary), len(idf))
            by_words = tf_idf(np.stack([self._term_counts[i] for i in ids]), idf) @ tf_idf(counts, idf)
            rankings.append([ids[j] for j in np.argsort(-by_words, kind="stable")[:k]])
        ordered = [i for group in zip(*rankings) for i in group]
        return list(dict.fromkeys(ordered))

    def _verify(self, query: _Query, entry: KeyframeEntry, intr: Intrinsics) -> Optional[Relocalization]:
        """PnP RANSAC of the frame's features against the keyframe's, back-projected into the world."""
        cfg = self.cfg
        if len(entry.descriptors) < cfg.min_inliers:
            return None
        pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(query.descriptors, entry.descriptors, k=2)
        good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < cfg.ratio * p[1].distance]
        if len(good) < cfg.min_inliers:
            return None
        qi = np.array([m.queryIdx for m in good])
        ki = np.array([m.trainIdx for m in good])
        world = entry.points_cam[ki] @ entry.pose[:3, :3].T + entry.pose[:3, 3]
        pixels = query.keypoints[qi].astype(np.float64)
        threshold = cfg.reprojection_px * intr.width / 640.0
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(world, pixels, intr.matrix(), None, iterationsCount=300,
                                                     reprojectionError=threshold, confidence=0.999,
                                                     flags=cv2.SOLVEPNP_AP3P)
        if not ok or inliers is None or len(inliers) < cfg.min_inliers:
            return None
        measured = query.depth[qi]
        sigma_z = cfg.depth_sigma_base + cfg.depth_sigma_quadratic * (measured - 0.4) ** 2
        pixel_sigma = cfg.pixel_sigma * intr.width / 640.0
        inlier = np.zeros(len(good), bool)
        inlier[inliers.reshape(-1)] = True
        # Refine on the inliers, then again on the inliers of the refined pose: reprojected within the threshold
        # and, where the frame has depth, at the depth it measured (within `depth_sigmas` of the sensor's noise).
        for _ in range(2):
            rvec, tvec = refine_with_depth(world[inlier], pixels[inlier], measured[inlier], sigma_z[inlier], rvec,
                                           tvec, intr, pixel_sigma)
            proj, z = project(world, rvec, tvec, intr)
            reprojected = (z > 0) & (np.linalg.norm(proj - pixels, axis=1) < threshold)
            has_depth = reprojected & (measured > 0)
            agree = has_depth & (np.abs(z - measured) <= cfg.depth_sigmas * sigma_z)
            inlier = reprojected & (agree | (measured <= 0))
            if inlier.sum() < cfg.min_inliers:
                return None
        agreement = float(agree.sum() / has_depth.sum()) if has_depth.any() else 0.0
        n_inliers = int(inlier.sum())
        if n_inliers < cfg.min_inlier_ratio * len(good) or agreement < cfg.min_depth_agreement:
            return None
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.reshape(3)
        return Relocalization(np.linalg.inv(w2c), entry.keyframe_id, n_inliers, len(good), agreement, 0.0)

    # -------------------------------------------------------------------------------------------- checkpoint
    def state_dict(self) -> dict:
        """Tensors and plain values only, so that it loads with torch.load(weights_only=True)."""
        return {
            "version": DATABASE_VERSION,
            "config": asdict(self.cfg),
            "seed": self.seed,
            "vocabulary": None if self._vocabulary is None else torch.from_numpy(self._vocabulary),
            "vocabulary_from": self._vocabulary_from,
            "keyframes": [
                {"id": e.keyframe_id, "keypoints": torch.from_numpy(e.keypoints),
                 "descriptors": torch.from_numpy(e.descriptors), "points_cam": torch.from_numpy(e.points_cam),
                 "thumbnail": torch.from_numpy(e.thumbnail), "pose": torch.from_numpy(e.pose)}
                for e in self.entries.values()
            ],
        }

    @staticmethod
    def from_state_dict(state: dict) -> "KeyframeDatabase":
        if not isinstance(state, dict) or state.get("version") != DATABASE_VERSION:
            found = state.get("version") if isinstance(state, dict) else type(state).__name__
            raise RelocalizationError(f"keyframe database version {found} is not supported (expected "
                                      f"{DATABASE_VERSION}); rebuild it from the map's keyframes")
        db = KeyframeDatabase(RelocalizationConfig(**state["config"]), seed=int(state["seed"]))
        if state["vocabulary"] is not None:
            db._vocabulary, db._vocabulary_from = state["vocabulary"].numpy(), int(state["vocabulary_from"])
            db._documents = np.zeros(len(db._vocabulary), np.int64)
        for kf in state["keyframes"]:
            db._insert(KeyframeEntry(int(kf["id"]), kf["keypoints"].numpy(), kf["descriptors"].numpy(),
                                     kf["points_cam"].numpy(), kf["thumbnail"].numpy(), kf["pose"].numpy()))
        return db


def _pose64(pose) -> np.ndarray:
    if pose is None:
        raise RelocalizationError("a keyframe needs its camera-to-world pose, got None; add it once it is tracked")
    pose = pose.detach().cpu().numpy() if isinstance(pose, torch.Tensor) else np.asarray(pose)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise RelocalizationError(f"pose must be a finite 4x4 camera-to-world matrix, got shape {pose.shape}")
    return pose.astype(np.float64)


def _checked_depth(depth: np.ndarray, shape: tuple[int, int], intr: Intrinsics) -> np.ndarray:
    depth = np.asarray(depth, dtype=np.float32)
    if depth.shape != shape or shape != (intr.height, intr.width):
        raise RelocalizationError(f"depth {depth.shape}, colour {shape} and intrinsics {intr.height}x{intr.width} "
                                  f"(height x width) must be the same size; resize the frame or scale the intrinsics")
    return np.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0)


def plausible_jump(found: np.ndarray, expected: np.ndarray, max_jump_m: float) -> bool:
    """Whether a pose found by the keyframes' features is near enough to where the camera is believed to be to be
    the same place (`relocalization.max_jump_m`): farther is another place that looks alike."""
    return float(np.linalg.norm(np.asarray(found)[:3, 3] - np.asarray(expected)[:3, 3])) <= max_jump_m
