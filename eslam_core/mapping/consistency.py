"""Depth consistency: how well a set of poses makes the frames' own depth images agree. Needs no ground truth.

For a pair of frames (a, b) that see the same surface, every depth pixel of a is back-projected, moved into b's
camera with the relative pose T_b^-1 T_a, projected, and its depth there compared with the depth b measured at that
point of its image (the residual r = warped depth - measured depth). With exact poses and exact depth r = 0; a pose
error moves the warped surface off the measured one. The score of a set of poses is the median |r| (mm) over all
compared pixels of all pairs, and the fraction of them that agree within `agree_m` (3 cm: a few times Kinect noise
at 2-3 m).

Occlusion. A warped point farther than b's measured surface by more than `agree_m` is hidden in b's view (b saw
something in front of it), so it is not compared. A warped point *in front of* b's surface counts as disagreement:
b looked through where a saw a surface. Dropping the hidden points alone would let a pose error hide itself (one
that pushes a's surface behind b's drops every point); so each pair is compared both ways: what is pushed behind
in a -> b comes out in front in b -> a, and counts there.

Pairs are chosen by view overlap of the poses, not by time alone: pairs a few frames apart (`near`, the local
consistency tracking must keep) and the latest later frame that sees the same surface as an earlier one (`far`,
revisits, where drift shows), see `choose_pairs`.

Measured depth is interpolated in b's image bilinearly in *inverse* depth, which is exact on planes (1/z is affine
in the pixel coordinates of a plane), and only where the four neighbours are valid and within `agree_m` of each
other (not across depth edges): exact poses on exact depth of a polyhedral scene score 0 to float precision.

`keyframe_consistency` is the cheap form for a running system: the newest keyframe against a few older ones.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch

from eslam_core.camera import Intrinsics, backproject

AGREE_M = 0.03  # residuals within this agree; farther behind the measured surface than this = occluded
NEAR_FRAMES = 10  # frames between the two frames of a `near` pair (1/3 s at 30 Hz)
FAR_FRAMES = 90  # a `far` pair is at least this many frames apart (3 s at 30 Hz)
MIN_OVERLAP = 0.5  # near pairs: both frames see at least this fraction of the other's sampled points
MIN_FAR_OVERLAP = 0.3  # far pairs (revisits from another viewpoint): a third of each view is still ~30k pixels


@dataclass(frozen=True)
class PairConsistency:
    """Depth agreement of one pair of frames under one set of poses (both directions pooled)."""

    first: int  # frame numbers (`frame_numbers` given to sequence_consistency, else positions)
    second: int
    kind: str  # "near" | "far" | "keyframe"
    median_mm: float  # median |residual|; nan when nothing could be compared
    agree_fraction: float  # fraction of compared pixels with |residual| <= agree_m; nan when nothing compared
    compared: int  # pixels compared
    occluded: int  # pixels hidden in the other view, not compared


@dataclass(frozen=True)
class ConsistencyResult:
    """The score of a set of poses over pairs of frames: pooled over all compared pixels of all pairs."""

    median_mm: float
    agree_fraction: float
    compared: int
    agree_m: float
    pairs: tuple[PairConsistency, ...]
    by_kind: dict  # kind -> (median_mm, agree_fraction, compared), pooled over that kind's pairs

    def summary(self) -> dict:
        """JSON-ready figures: overall, and per kind of pair (near / far)."""
        return {
            "median_mm": self.median_mm,
            "agree_percent": 100.0 * self.agree_fraction,
            "agree_within_cm": 100.0 * self.agree_m,
            "pairs": len(self.pairs),
            "compared_pixels": self.compared,
            "by_kind": {
                kind: {"pairs": sum(p.kind == kind for p in self.pairs), "median_mm": median,
                       "agree_percent": 100.0 * agree, "compared_pixels": compared}
                for kind, (median, agree, compared) in sorted(self.by_kind.items())
            },
        }


# ---------------------------------------------------------------------------------------------------------------
# One direction of one pair
#
# numpy, not torch: the images are small and the work is a few element-wise passes, which torch's thread pool made
# 25x slower on a loaded 2-core machine (12 ms for a torch.floor of 5000 values).


def as_depth_metres(depth, depth_scale: Optional[float] = None) -> np.ndarray:
    """float64 metres of depth values in metres (float) or raw units (integer, needs `depth_scale`), any shape;
    torch tensors or numpy arrays. int16 values are read as the uint16 bits they hold (the keyframe store's)."""
    array = _image(depth)
    if array.dtype.kind == "f":
        return np.asarray(array, dtype=np.float64)  # no copy when it is float64 already
    if array.dtype.kind not in "ui":
        raise ValueError(f"a depth image must hold numbers, got dtype {array.dtype}")
    if depth_scale is None:
        raise ValueError("integer depth images need depth_scale (raw units per metre, e.g. 1000 for millimetres)")
    raw = array.astype(np.uint16) if array.dtype == np.int16 else array  # wraps: the uint16 bits
    return raw.astype(np.float64) / float(depth_scale)


def _image(depth) -> np.ndarray:
    """A numpy view of a depth image (a CPU torch tensor without a copy)."""
    return depth.detach().cpu().numpy() if isinstance(depth, torch.Tensor) else np.asarray(depth)


def _sampled_points(depth: np.ndarray, intrinsics: Intrinsics, stride: int, camera_to: np.ndarray,
                    depth_scale: Optional[float], max_depth: float = 0.0) -> np.ndarray:
    """Points (N, 3) of every `stride`-th pixel's depth, moved by `camera_to` (4x4). Only those pixels are read:
    full-image pixel k * stride is pixel k of a camera with the intrinsics divided by the stride."""
    sampled = as_depth_metres(depth[::stride, ::stride], depth_scale)
    if max_depth > 0:
        sampled = np.where(sampled <= max_depth, sampled, 0.0)
    i = intrinsics
    grid = Intrinsics(sampled.shape[1], sampled.shape[0], i.fx / stride, i.fy / stride, i.cx / stride, i.cy / stride)
    return backproject(sampled, grid, np.asarray(camera_to, dtype=np.float64))


def _pixels(points: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) of camera points (N, 3) with z > 0 (the numpy form of Intrinsics.project)."""
    z = np.maximum(points[:, 2], 1e-6)
    return (intrinsics.fx * points[:, 0] / z + intrinsics.cx, intrinsics.fy * points[:, 1] / z + intrinsics.cy)


def _measured_depth_at(depth: np.ndarray, u: np.ndarray, v: np.ndarray, edge_m: float,
                       depth_scale: Optional[float], max_depth: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Depth (metres) of image `depth` at sub-pixel (u, v), bilinear in inverse depth, and where it is defined:
    inside the image, all four neighbours measured (and within max_depth, if > 0) and within `edge_m` of each other
    (not across a depth edge). Only the neighbours are read and converted."""
    height, width = depth.shape
    u0, v0 = np.floor(u), np.floor(v)
    inside = (u0 >= 0) & (v0 >= 0) & (u0 <= width - 2) & (v0 <= height - 2)
    iu = np.clip(u0, 0, width - 2).astype(np.int64)
    iv = np.clip(v0, 0, height - 2).astype(np.int64)
    corners = as_depth_metres(
        np.stack([depth[iv, iu], depth[iv, iu + 1], depth[iv + 1, iu], depth[iv + 1, iu + 1]], axis=-1), depth_scale)
    measured = corners > 0
    if max_depth > 0:
        measured &= corners <= max_depth
    valid = inside & measured.all(axis=-1) & (np.ptp(corners, axis=-1) <= edge_m)
    fu, fv = np.clip(u - u0, 0, 1), np.clip(v - v0, 0, 1)
    weights = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], axis=-1)
    inverse = (weights / np.where(corners > 0, corners, 1.0)).sum(axis=-1)
    return 1.0 / inverse, valid


def warp_residuals(
    depth_source,
    depth_target,
    source_to_target: np.ndarray,
    intrinsics: Intrinsics,
    *,
    agree_m: float = AGREE_M,
    stride: int = 4,
    max_depth: float = 0.0,
    depth_scale: Optional[float] = None,
) -> tuple[np.ndarray, int]:
    """Signed residuals (metres, warped minus measured) of the source's depth pixels that the target camera saw,
    and the number of source pixels hidden in the target view (behind its measured surface by more than agree_m).

    `source_to_target` = T_target^-1 @ T_source (camera-to-world poses). Every `stride`-th source pixel is used;
    depth beyond `max_depth` (0 = no cut) is not used in either image. Depths are metres, or raw integer units
    with `depth_scale`; the cost is in the sampled pixels, not the image size.
    """
    points = _sampled_points(_image(depth_source), intrinsics, stride, source_to_target, depth_scale, max_depth)
    u, v = _pixels(points, intrinsics)
    measured, seen = _measured_depth_at(_image(depth_target), u, v, agree_m, depth_scale, max_depth)
    seen &= points[:, 2] > 0
    residual = points[:, 2] - measured
    hidden = seen & (residual > agree_m)
    return residual[seen & ~hidden], int(hidden.sum())


def pair_consistency(
    depth_a, depth_b, pose_a: np.ndarray, pose_b: np.ndarray, intrinsics: Intrinsics, *,
    first: int = 0, second: int = 1, kind: str = "near", agree_m: float = AGREE_M, stride: int = 4,
    max_depth: float = 0.0, depth_scale: Optional[float] = None,
) -> tuple[PairConsistency, np.ndarray]:
    """Both directions of one pair: its figures and the pooled |residuals| (metres, float32)."""
    pose_a, pose_b = np.asarray(pose_a, dtype=np.float64), np.asarray(pose_b, dtype=np.float64)
    a_to_b = np.linalg.solve(pose_b, pose_a)  # T_b^-1 T_a
    options = dict(agree_m=agree_m, stride=stride, max_depth=max_depth, depth_scale=depth_scale)
    forward, hidden_forward = warp_residuals(depth_a, depth_b, a_to_b, intrinsics, **options)
    backward, hidden_backward = warp_residuals(depth_b, depth_a, np.linalg.inv(a_to_b), intrinsics, **options)
    residuals = np.abs(np.concatenate([forward, backward])).astype(np.float32)
    median, agree = _figures(residuals, agree_m)
    return PairConsistency(first, second, kind, median, agree, len(residuals),
                           hidden_forward + hidden_backward), residuals


def _figures(abs_residuals: np.ndarray, agree_m: float) -> tuple[float, float]:
    if len(abs_residuals) == 0:
        return math.nan, math.nan
    return float(np.median(abs_residuals) * 1000.0), float(np.mean(abs_residuals <= agree_m))


# ---------------------------------------------------------------------------------------------------------------
# Choosing pairs by view overlap


def view_overlap(depth_a, pose_a: np.ndarray, pose_b: np.ndarray, intrinsics: Intrinsics, *,
                 samples_across: int = 30, depth_scale: Optional[float] = None) -> float:
    """Fraction of a's depth points (about `samples_across` pixels along the shorter image side, so ~1200 at 4:3)
    that fall inside b's image, in front of b."""
    a_to_b = np.linalg.solve(np.asarray(pose_b, np.float64), np.asarray(pose_a, np.float64))
    depth = _image(depth_a)
    points = _sampled_points(depth, intrinsics, max(1, min(depth.shape) // samples_across), a_to_b, depth_scale)
    if len(points) == 0:
        return 0.0
    u, v = _pixels(points, intrinsics)
    inside = (points[:, 2] > 0) & (u >= 0) & (u <= intrinsics.width - 1) & (v >= 0) & (v <= intrinsics.height - 1)
    return float(inside.mean())


def mutual_overlap(depth_a, depth_b, pose_a, pose_b, intrinsics: Intrinsics, *, samples_across: int = 30,
                   depth_scale: Optional[float] = None) -> float:
    """The smaller of the two views' overlaps: both frames must see much of what the other sees."""
    options = dict(samples_across=samples_across, depth_scale=depth_scale)
    return min(view_overlap(depth_a, pose_a, pose_b, intrinsics, **options),
               view_overlap(depth_b, pose_b, pose_a, intrinsics, **options))


def choose_pairs(
    depths: Sequence, poses: np.ndarray, frame_numbers: Sequence[int], intrinsics: Intrinsics, *,
    near_frames: int = NEAR_FRAMES, far_frames: int = FAR_FRAMES, min_overlap: float = MIN_OVERLAP,
    min_far_overlap: float = MIN_FAR_OVERLAP, depth_scale: Optional[float] = None,
) -> list[tuple[int, int, str]]:
    """Pairs (k, m, kind) of positions in `depths` / `poses` that see the same surface.

    `frame_numbers` are the frames' numbers in the sequence (the depths may be every n-th frame). For each frame k:
    - near: the first later frame at least `near_frames` frames on, if the two overlap by `min_overlap`;
    - far: the latest later frame at least `far_frames` frames on that overlaps by `min_far_overlap` (a revisit
      when the camera came back; drift between the two shows as disagreement).
    Overlap is measured with `poses`; to compare two sets of poses fairly, choose the pairs once and score both.
    """
    numbers = np.asarray(frame_numbers, dtype=np.int64)
    if len(depths) != len(poses) or len(poses) != len(numbers):
        raise ValueError(f"choose_pairs needs as many depths, poses and frame numbers, got "
                         f"{len(depths)}, {len(poses)}, {len(numbers)}")
    overlap_cache: dict[tuple[int, int], float] = {}

    def overlap(k: int, m: int) -> float:
        if (k, m) not in overlap_cache:
            overlap_cache[(k, m)] = mutual_overlap(depths[k], depths[m], poses[k], poses[m], intrinsics,
                                                   depth_scale=depth_scale)
        return overlap_cache[(k, m)]

    pairs: list[tuple[int, int, str]] = []
    for k in range(len(numbers)):
        later = np.flatnonzero(numbers >= numbers[k] + near_frames)
        if later.size and overlap(k, int(later[0])) >= min_overlap:
            pairs.append((k, int(later[0]), "near"))
        for m in np.flatnonzero(numbers >= numbers[k] + far_frames)[::-1]:
            if overlap(k, int(m)) >= min_far_overlap:
                pairs.append((k, int(m), "far"))
                break
    return pairs


# ---------------------------------------------------------------------------------------------------------------
# Scores of a sequence


def sequence_consistency(
    depths: Sequence, poses: np.ndarray, pairs: Sequence[tuple[int, int, str]], intrinsics: Intrinsics, *,
    frame_numbers: Optional[Sequence[int]] = None, agree_m: float = AGREE_M, stride: int = 4,
    max_depth: float = 0.0, depth_scale: Optional[float] = None,
) -> ConsistencyResult:
    """The consistency score of `poses` (N, 4, 4 camera-to-world) over the given pairs of positions.

    Pairs whose pose is missing (non-finite) are skipped. `frame_numbers` name the frames in the result's pairs
    (default: positions).
    """
    poses = np.asarray(poses, dtype=np.float64)
    numbers = list(range(len(poses))) if frame_numbers is None else [int(n) for n in frame_numbers]
    results, pooled, kinds = [], [], []
    for k, m, kind in pairs:
        if not (np.isfinite(poses[k]).all() and np.isfinite(poses[m]).all()):
            continue
        pair, residuals = pair_consistency(depths[k], depths[m], poses[k], poses[m], intrinsics,
                                           first=numbers[k], second=numbers[m], kind=kind, agree_m=agree_m,
                                           stride=stride, max_depth=max_depth, depth_scale=depth_scale)
        results.append(pair)
        pooled.append(residuals)
        kinds.append(kind)
    by_kind = {}
    for kind in sorted(set(kinds)):
        of_kind = np.concatenate([r for r, k in zip(pooled, kinds) if k == kind])
        by_kind[kind] = (*_figures(of_kind, agree_m), len(of_kind))
    everything = np.concatenate(pooled) if pooled else np.zeros(0, dtype=np.float32)
    median, agree = _figures(everything, agree_m)
    return ConsistencyResult(median, agree, len(everything), agree_m, tuple(results), by_kind)


@dataclass(frozen=True)
class KeyframeConsistency:
    """What the runtime's health reports: the newest keyframe's depth against older keyframes'."""

    median_mm: float  # nan when no pair could be compared
    agree_fraction: float
    pairs: int
    compared: int


def keyframe_consistency(
    depths: Sequence, poses: Sequence, intrinsics: Intrinsics, *, depth_scale: Optional[float] = None,
    max_pairs: int = 4, min_overlap: float = MIN_OVERLAP, agree_m: float = AGREE_M, stride: int = 8,
) -> KeyframeConsistency:
    """Depth consistency of the newest keyframe (the last of `depths` / `poses`, oldest first) with older ones.

    Pairs: the previous keyframe (local consistency) and up to `max_pairs - 1` of the oldest keyframes that still
    overlap the newest by `min_overlap` (drift since the camera was last there). Images are float metres or
    integer raw units with `depth_scale` (torch or numpy, full frame resolution); poses 4x4 camera-to-world.
    Cost (640x480, 4 pairs, every 8th pixel, overlap on ~300 points per keyframe; only the pixels sampled are
    read): 10 ms with 8 keyframes, 13 ms with 40, on the loaded 2-core machine; stride 16 about 4-8 ms.
    """
    n = len(depths)
    if n != len(poses):
        raise ValueError(f"keyframe_consistency needs one pose per depth image, got {n} and {len(poses)}")
    poses = [np.asarray(p.detach().cpu() if isinstance(p, torch.Tensor) else p, dtype=np.float64) for p in poses]
    if n < 2 or max_pairs < 1:
        return KeyframeConsistency(math.nan, math.nan, 0, 0)
    newest = n - 1
    chosen = [newest - 1]
    for k in range(newest - 1):
        if len(chosen) >= max_pairs:
            break
        if mutual_overlap(depths[k], depths[newest], poses[k], poses[newest], intrinsics, samples_across=15,
                          depth_scale=depth_scale) >= min_overlap:
            chosen.append(k)
    pairs = [(k, newest, "keyframe") for k in chosen]
    result = sequence_consistency(depths, np.stack(poses), pairs, intrinsics, agree_m=agree_m, stride=stride,
                                  depth_scale=depth_scale)
    return KeyframeConsistency(result.median_mm, result.agree_fraction, len(result.pairs), result.compared)
