"""TUM RGB-D sequences, and ICL-NUIM sequences stored in the TUM layout.

A TUM folder holds `rgb.txt` and `depth.txt` (`timestamp filename` per line) and optionally `groundtruth.txt`
(`timestamp tx ty tz qx qy qz qw`, camera-to-world). Colour and depth are captured by separate streams at
slightly different times, so frames are built by associating each colour image with the depth image nearest in
time; an `associations.txt` written beforehand (as ICL-NUIM ships) replaces that step.

TUM images have lens distortion (a few pixels at the border on freiburg1/2). ESLAM, like the official
implementation, ignores it: images are returned undistorted-as-is with the pinhole intrinsics only.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np

from eslam_core.camera import Intrinsics
from eslam_core.geometry import matrix_to_quaternion_xyzw, quaternion_xyzw_to_matrix
from eslam_core.trajectory import Trajectory, TrajectoryError
from eslam_core.datasets.base import (
    DatasetError,
    FrameFiles,
    RGBDDataset,
    parse_floats,
    read_text_rows,
    require_dir,
    resolve_depth_scale,
)

# Colour and depth (and ground truth) closer in time than this are taken to be the same instant (TUM's own tools
# use the same 20 ms).
MAX_TIME_DIFFERENCE = 0.02

TUM_DEPTH_SCALE = 5000.0

# Factory calibration of the three Kinects used for the TUM RGB-D benchmark (pinhole part only).
TUM_FREIBURG_INTRINSICS = {
    "freiburg1": Intrinsics(640, 480, fx=517.3, fy=516.5, cx=318.6, cy=255.3),
    "freiburg2": Intrinsics(640, 480, fx=520.9, fy=521.0, cx=325.1, cy=249.7),
    "freiburg3": Intrinsics(640, 480, fx=535.4, fy=539.2, cx=320.1, cy=247.6),
}

ICL_NUIM_INTRINSICS = Intrinsics(640, 480, fx=481.20, fy=480.00, cx=319.50, cy=239.50)

# ICL-NUIM poses are written for a camera whose y axis points up; conjugating by this flip turns them into
# OpenCV-axis poses consistent with the (positive fy) images.
ICL_Y_FLIP = np.diag([1.0, -1.0, 1.0, 1.0])


# --- the math ---------------------------------------------------------------------------------------------------


def rotation_from_quaternion(qx: float, qy: float, qz: float, qw: float) -> np.ndarray:
    """3x3 rotation of a (not necessarily normalised) Hamilton quaternion."""
    q = np.array([qx, qy, qz, qw], dtype=np.float64)
    if not np.linalg.norm(q) > 0:
        raise ValueError("quaternion has zero length")
    return quaternion_xyzw_to_matrix(q)


def pose_from_tum(tx: float, ty: float, tz: float, qx: float, qy: float, qz: float, qw: float) -> np.ndarray:
    """4x4 camera-to-world pose of one TUM trajectory line."""
    pose = np.eye(4)
    pose[:3, :3] = rotation_from_quaternion(qx, qy, qz, qw)
    pose[:3, 3] = (tx, ty, tz)
    return pose


def icl_to_opencv(pose_file: np.ndarray) -> np.ndarray:
    """ICL-NUIM ground truth (y up) to OpenCV axes: T = F @ T_file @ F with F = diag(1, -1, 1, 1)."""
    return ICL_Y_FLIP @ pose_file @ ICL_Y_FLIP


def associate_timestamps(first: np.ndarray, second: np.ndarray, max_difference: float) -> np.ndarray:
    """Index pairs (M, 2) with |first[i] - second[j]| <= max_difference, each index used at most once.

    As TUM's associate.py: candidate pairs are accepted closest-first, so when two colour images compete for one
    depth image the nearer one gets it and the other is dropped (or takes its next-best partner). Ordered by the
    time of `first`. This is the one pairing of two clocks: the TUM reader pairs colour with depth by it, the
    trajectory metrics an estimate with the ground truth. Empty (shape (0, 2)) when nothing pairs.
    """
    first = np.asarray(first, dtype=np.float64)
    second = np.asarray(second, dtype=np.float64)
    tolerance = max_difference + 1e-9  # timestamps are printed decimals: do not lose exact-boundary pairs
    order = np.argsort(second, kind="stable")
    second_sorted = second[order]
    lo = np.searchsorted(second_sorted, first - tolerance, side="left")
    hi = np.searchsorted(second_sorted, first + tolerance, side="right")
    counts = hi - lo
    first_index = np.repeat(np.arange(len(first)), counts)
    # Position of each candidate inside its window: a running index reset at each window start.
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    second_index = order[np.repeat(lo, counts) + offsets]
    gap = np.abs(first[first_index] - second[second_index])

    used_first = np.zeros(len(first), dtype=bool)
    used_second = np.zeros(len(second), dtype=bool)
    pairs = []
    for k in np.lexsort((second_index, first_index, gap)):
        i, j = first_index[k], second_index[k]
        if not used_first[i] and not used_second[j]:
            used_first[i] = used_second[j] = True
            pairs.append((i, j))
    pairs = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    return pairs[np.lexsort((pairs[:, 0], first[pairs[:, 0]]))]


def nearest_within(queries: np.ndarray, references: np.ndarray, max_difference: float) -> np.ndarray:
    """For each query, the index of the nearest reference within max_difference, else -1 (references reusable)."""
    queries = np.asarray(queries, dtype=np.float64)
    references = np.asarray(references, dtype=np.float64)
    result = np.full(len(queries), -1, dtype=np.int64)
    if len(references) == 0:
        return result
    order = np.argsort(references, kind="stable")
    sorted_refs = references[order]
    right = np.clip(np.searchsorted(sorted_refs, queries), 0, len(sorted_refs) - 1)
    left = np.clip(right - 1, 0, len(sorted_refs) - 1)
    pick = np.where(np.abs(sorted_refs[left] - queries) <= np.abs(sorted_refs[right] - queries), left, right)
    close = np.abs(sorted_refs[pick] - queries) <= max_difference + 1e-9
    result[close] = order[pick[close]]
    return result


# --- the files --------------------------------------------------------------------------------------------------


def read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """Timestamps and relative file names of a TUM `rgb.txt` / `depth.txt`."""
    rows = read_text_rows(path, 2, "TUM file list (`timestamp filename` per line)")
    timestamps = np.array([parse_floats(fields[:1], path, n)[0] for n, fields in rows], dtype=np.float64)
    return timestamps, [fields[1] for _, fields in rows]


def read_associations(path: Path) -> tuple[np.ndarray, list[str], list[str]]:
    """(colour timestamps, colour files, depth files) of an `associations.txt`.

    ICL-NUIM writes `t_depth depth_file t_rgb rgb_file`; TUM's associate.py run as `associate.py rgb.txt
    depth.txt` writes colour first. The order is taken from which column names a depth folder.
    """
    rows = read_text_rows(path, 4, "association file (`t_depth depth_file t_rgb rgb_file` per line)")
    if not rows:
        return np.zeros(0), [], []
    _, first_row = rows[0]
    colour_first = "depth" in first_row[3].lower() and "depth" not in first_row[1].lower()
    rgb_col, depth_col = (0, 2) if colour_first else (2, 0)
    timestamps = np.array([parse_floats([f[rgb_col]], path, n)[0] for n, f in rows], dtype=np.float64)
    return timestamps, [f[rgb_col + 1] for _, f in rows], [f[depth_col + 1] for _, f in rows]


def read_tum_trajectory(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (N,) and camera-to-world poses (N, 4, 4), as written (no axis change), of a TUM trajectory file
    (`timestamp tx ty tz qx qy qz qw` per line; `#` comments, spaces or commas). The one reader of the format:
    ground truth of TUM / ICL-NUIM folders and the trajectories the evaluation compares."""
    rows = read_text_rows(path, 8, "TUM trajectory (`timestamp tx ty tz qx qy qz qw` per line)")
    timestamps, poses = [], []
    for line_number, fields in rows:
        values = parse_floats(fields, path, line_number)
        if not np.all(np.isfinite(values)):
            raise DatasetError(
                f"{path}, line {line_number}: pose at timestamp {fields[0]} is not finite (nan/inf); the "
                f"estimator lost track there: fix or delete the line"
            )
        try:
            # rotation_from_quaternion normalises: files often carry rounded, non-unit quaternions
            poses.append(pose_from_tum(*values[1:]))
        except ValueError:
            raise DatasetError(
                f"{path}, line {line_number}: the quaternion qx qy qz qw is all zeros; fix or delete the line"
            ) from None
        timestamps.append(values[0])
    return np.array(timestamps, dtype=np.float64), np.array(poses, dtype=np.float64).reshape(-1, 4, 4)


def read_camera_json(path: Path) -> tuple[Intrinsics, Optional[float]]:
    """Intrinsics and optional depth scale of a `camera.json` ({"width","height","fx","fy","cx","cy","depth_scale"})."""
    try:
        values = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise DatasetError(f"cannot read camera file {path} ({err}); fix the JSON or delete the file") from None
    required = ("width", "height", "fx", "fy", "cx", "cy")
    missing = [key for key in required if not isinstance(values, dict) or key not in values]
    if missing:
        raise DatasetError(f"camera file {path} lacks {', '.join(missing)}; it needs keys {', '.join(required)}")
    try:
        intrinsics = Intrinsics(
            int(values["width"]), int(values["height"]),
            float(values["fx"]), float(values["fy"]), float(values["cx"]), float(values["cy"]),
        )
        depth_scale = None if values.get("depth_scale") is None else float(values["depth_scale"])
    except (TypeError, ValueError) as err:
        raise DatasetError(f"camera file {path} has an invalid value ({err}); fix the file") from None
    return intrinsics, depth_scale


# --- the readers ------------------------------------------------------------------------------------------------


class TUMDataset(RGBDDataset):
    """A TUM RGB-D sequence folder (`rgb.txt`, `depth.txt` or `associations.txt`, optional `groundtruth.txt`).

    Intrinsics, first found wins: the `intrinsics` argument, the folder's `camera.json`, the standard Kinect
    calibration when the folder name contains freiburg1/2/3. Lens distortion is ignored (see module docstring).
    """

    kind = "tum"

    def __init__(self, root: Path | str, intrinsics: Optional[Intrinsics] = None,
                 depth_scale: Optional[float] = None) -> None:
        root = Path(root)
        require_dir(root, "TUM sequence folder", "pass the folder that holds rgb.txt and depth.txt")
        rgb_times, rgb_files, depth_files, index_files = self._read_frame_list(root)
        poses = self._poses_at(root, rgb_times)

        found_intrinsics, found_scale = None, None
        camera_json = root / "camera.json"
        if camera_json.is_file():
            found_intrinsics, found_scale = read_camera_json(camera_json)
        resolved = intrinsics or found_intrinsics or self._default_intrinsics(root)
        if resolved is None:
            raise DatasetError(
                f"no camera intrinsics for {root}: it has no camera.json and its name does not say which TUM "
                f"camera (freiburg1/2/3) took it; pass intrinsics (config `camera:` section: width, height, "
                f"fx, fy, cx, cy)"
            )
        records = [
            FrameFiles(float(t), root / rgb_file, root / depth_file, pose)
            for t, rgb_file, depth_file, pose in zip(rgb_times, rgb_files, depth_files, poses)
        ]
        self._setup(root, root.resolve().name, resolved, resolve_depth_scale(depth_scale, found_scale, TUM_DEPTH_SCALE),
                    records, index_files)

    def _default_intrinsics(self, root: Path) -> Optional[Intrinsics]:
        folder = root.resolve().name.lower()
        for camera, intrinsics in TUM_FREIBURG_INTRINSICS.items():
            if camera in folder:
                return intrinsics
        return None

    def _ground_truth_pose(self, pose_file: np.ndarray) -> np.ndarray:
        """A ground-truth pose as written in groundtruth.txt, in OpenCV axes (TUM already is)."""
        return pose_file

    def _groundtruth_file(self, root: Path) -> Optional[Path]:
        path = root / "groundtruth.txt"
        return path if path.is_file() else None

    def _read_frame_list(self, root: Path) -> tuple[np.ndarray, list[str], list[str], str]:
        """(colour timestamps, colour files, depth files, names of the files read) of the frames, in time order."""
        associations = root / "associations.txt"
        if associations.is_file():
            times, rgb_files, depth_files = read_associations(associations)
            return times, rgb_files, depth_files, str(associations)
        rgb_list, depth_list = root / "rgb.txt", root / "depth.txt"
        for listing in (rgb_list, depth_list):
            if not listing.is_file():
                raise DatasetError(
                    f"missing TUM file list: {listing} not found; a TUM sequence needs rgb.txt and depth.txt "
                    f"(or an associations.txt)"
                )
        rgb_times, rgb_files = read_file_list(rgb_list)
        depth_times, depth_files = read_file_list(depth_list)
        pairs = associate_timestamps(rgb_times, depth_times, MAX_TIME_DIFFERENCE)
        if rgb_times.size and depth_times.size and not len(pairs):
            raise DatasetError(
                f"no colour image in {rgb_list} has a depth image in {depth_list} within {MAX_TIME_DIFFERENCE} s; "
                f"check that both lists belong to the same recording, or write an associations.txt"
            )
        return (
            np.array([rgb_times[i] for i, _ in pairs], dtype=np.float64),
            [rgb_files[i] for i, _ in pairs],
            [depth_files[j] for _, j in pairs],
            f"{rgb_list} and {depth_list}",
        )

    def _poses_at(self, root: Path, times: np.ndarray) -> list[Optional[np.ndarray]]:
        """Ground truth nearest in time to each frame (within MAX_TIME_DIFFERENCE), None without groundtruth.txt."""
        groundtruth = self._groundtruth_file(root)
        if groundtruth is None:
            return [None] * len(times)
        gt_times, gt_poses = read_tum_trajectory(groundtruth)
        nearest = nearest_within(times, gt_times, MAX_TIME_DIFFERENCE)
        return [None if k < 0 else self._ground_truth_pose(gt_poses[k]) for k in nearest]


class ICLNUIMDataset(TUMDataset):
    """ICL-NUIM in the TUM layout: frame numbers as timestamps, known intrinsics, y-up ground truth.

    Ground truth (groundtruth.txt, or the `<scene>.gt.freiburg` of ICL-NUIM's downloads) may start after the first
    image (trajectory 0 of "office" has none for frame 1): such frames get pose None. Poses are converted to OpenCV axes with `icl_to_opencv`.
    """

    kind = "icl"

    def _default_intrinsics(self, root: Path) -> Optional[Intrinsics]:
        return ICL_NUIM_INTRINSICS

    def _ground_truth_pose(self, pose_file: np.ndarray) -> np.ndarray:
        return icl_to_opencv(pose_file)

    def _groundtruth_file(self, root: Path) -> Optional[Path]:
        """groundtruth.txt, else the single `*.gt.freiburg` file ICL-NUIM's own downloads ship (same format)."""
        path = super()._groundtruth_file(root)
        if path is not None:
            return path
        freiburg = sorted(root.glob("*.gt.freiburg"))
        if len(freiburg) > 1:
            raise DatasetError(
                f"{root} holds several ground-truth files ({', '.join(f.name for f in freiburg)}); "
                f"keep the one of this sequence, or copy it to groundtruth.txt"
            )
        return freiburg[0] if freiburg else None


# ---------------------------------------------------------------------------------------------------------------
# TUM trajectory files of `Trajectory`s (the product's trajectory output and the files the evaluation reads)


def read_tum(path: Path | str) -> Trajectory:
    """Read a TUM trajectory file (`timestamp tx ty tz qx qy qz qw` per line, `#` comments, spaces or commas).

    The format has one reader, `read_tum_trajectory`; its errors become TrajectoryErrors.
    """
    path = Path(path)
    if not path.is_file():
        raise TrajectoryError(f"trajectory file not found: {path}")
    try:
        timestamps, poses = read_tum_trajectory(path)
    except DatasetError as error:
        raise TrajectoryError(str(error)) from None
    if not len(timestamps):
        raise TrajectoryError(f"{path} contains no poses (expected lines 'timestamp tx ty tz qx qy qz qw')")
    return Trajectory(timestamps, poses)


def write_tum(path: Path | str, trajectory: Trajectory) -> Path:
    """Write a TUM trajectory file; returns its path."""
    path = Path(path)
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for timestamp, pose in zip(trajectory.timestamps, trajectory.poses):
        q = matrix_to_quaternion_xyzw(pose[:3, :3])
        t = pose[:3, 3]
        lines.append(
            f"{timestamp:.6f} {t[0]:.9f} {t[1]:.9f} {t[2]:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}"
        )
    path.write_text("\n".join(lines) + "\n")
    return path
