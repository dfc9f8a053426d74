"""Microsoft 7-Scenes sequences (one `seq-XX/` folder of a scene such as `chess/`), as released and as re-shipped.

    seq-01/frame-000000.color.png   640x480 colour (.color.jpg in the widely used re-packaged copies)
    seq-01/frame-000000.depth.png   640x480 uint16 millimetres; 65535 (original release) or 0 = no measurement
    seq-01/frame-000000.pose.txt    4x4 camera-to-world (from KinectFusion)
    camera-intrinsics.txt           optional 3x3 depth camera matrix, in the sequence folder or its scene folder

7-Scenes colour and depth come from the Kinect's two cameras and are NOT registered: the colour camera has a wider
view (focal length about 525 pixels against the depth camera's 585, the values DSAC and later work use), so the
same pixel coordinates see points up to ~30 pixels apart towards the image edges. The reader resamples the colour
image onto the depth camera's pixels (`register_colour`, the baseline between the cameras ignored: it is not
published); `dataset.register_colour: false` keeps the colour as shipped. Intrinsics are those of
camera-intrinsics.txt when present, else the nominal ones the data set documents for depth. Frames are
recorded at 30 Hz without timestamps, so a frame's timestamp is its number (the NNNNNN in its file names) / 30.
KinectFusion's rotations are orthonormal only to about 1e-4; they are re-orthonormalised (`checked_pose`).
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Optional

import numpy as np

from eslam_core.camera import Intrinsics
from eslam_core.datasets.base import (
    DatasetError,
    FrameFiles,
    RGBDDataset,
    checked_pose,
    image_size,
    intrinsics_from_matrix,
    numbered_files,
    read_depth_raw,
    read_matrix,
    read_matrix4x4,
    require_dir,
    resolve_depth_scale,
)

SEVEN_SCENES_INTRINSICS = Intrinsics(640, 480, fx=585.0, fy=585.0, cx=320.0, cy=240.0)
SEVEN_SCENES_COLOUR_INTRINSICS = Intrinsics(640, 480, fx=525.0, fy=525.0, cx=320.0, cy=240.0)
SEVEN_SCENES_DEPTH_SCALE = 1000.0
SEVEN_SCENES_FRAME_RATE = 30.0
SEVEN_SCENES_INVALID_DEPTH = 65535  # the original release's raw value for "no measurement" (copies also use 0)
INTRINSICS_FILE = "camera-intrinsics.txt"

# PNG first: where a frame has both, the lossless one is read.
COLOUR_SUFFIXES = (".color.png", ".color.jpg", ".color.jpeg")
_DEPTH_NAME = re.compile(r"^frame-(\d+)\.depth\.png$")
_COLOUR_NAMES = [re.compile(rf"^frame-(\d+){re.escape(suffix)}$", re.IGNORECASE) for suffix in COLOUR_SUFFIXES]


def colour_files(folder: Path) -> dict[int, Path]:
    """Frame number -> colour image (.color.png, else .color.jpg / .jpeg) of a sequence folder."""
    found: dict[int, Path] = {}
    for pattern in reversed(_COLOUR_NAMES):  # later suffixes are overwritten by earlier ones
        found.update(numbered_files(folder, pattern))
    return found


def has_frames(folder: Path) -> bool:
    """Whether `folder` holds 7-Scenes colour images (any accepted suffix); used by format detection."""
    return folder.is_dir() and any(
        pattern.match(child.name) for child in folder.iterdir() for pattern in _COLOUR_NAMES
    )


def read_intrinsics_file(folder: Path, depth_file: Path) -> Optional[Intrinsics]:
    """The camera matrix of `camera-intrinsics.txt` in the sequence folder or its scene folder, None if absent."""
    for candidate in (folder / INTRINSICS_FILE, folder.resolve().parent / INTRINSICS_FILE):
        if candidate.is_file():
            matrix = read_matrix(candidate, 3, "7-Scenes camera matrix (3 lines of 3 numbers)")
            width, height = image_size(depth_file, "depth image")
            return intrinsics_from_matrix(matrix, width, height, candidate)
    return None


def _reject_scene_folder(path: Path) -> None:
    """Point a user who passed a scene folder (chess/) at its sequences (chess/seq-01/)."""
    sequences = sorted(child.name for child in path.glob("seq-*") if child.is_dir())
    if sequences:
        raise DatasetError(
            f"{path} is a 7-Scenes scene folder holding sequences {', '.join(sequences)}; "
            f"pass one sequence folder, e.g. {path / sequences[0]}"
        )


class SevenScenesDataset(RGBDDataset):
    """One 7-Scenes sequence folder; frames are the colour/depth pairs present, in frame-number order.

    A frame without a pose file, or with a non-finite pose, gets pose None. `intrinsics` (the config's `camera:`
    section) wins over camera-intrinsics.txt, which wins over the nominal SEVEN_SCENES_INTRINSICS.
    """

    kind = "7scenes"
    colour_intrinsics = SEVEN_SCENES_COLOUR_INTRINSICS

    def __init__(self, path: Path | str, intrinsics: Optional[Intrinsics] = None,
                 depth_scale: Optional[float] = None) -> None:
        path = Path(path)
        require_dir(path, "7-Scenes sequence folder", "pass a seq-XX folder holding frame-NNNNNN.color.png files")
        colour = colour_files(path)
        depth = numbered_files(path, _DEPTH_NAME)
        if not colour and not depth:
            _reject_scene_folder(path)
        records = []
        for k in sorted(colour.keys() & depth.keys()):
            pose_file = path / f"{colour[k].name.split('.')[0]}.pose.txt"  # frame-NNNNNN, as the images spell it
            pose = checked_pose(read_matrix4x4(pose_file, "7-Scenes pose"), pose_file) if pose_file.is_file() else None
            records.append(FrameFiles(k / SEVEN_SCENES_FRAME_RATE, colour[k], depth[k], pose))
        if intrinsics is None and records:
            intrinsics = read_intrinsics_file(path, records[0].depth_path)
        resolved = path.resolve()
        # seq-01 alone does not say which scene it is: prefix its scene folder (chess-seq-01)
        name = f"{resolved.parent.name}-{resolved.name}" if resolved.name.startswith("seq-") else resolved.name
        self._setup(
            path, name, intrinsics or SEVEN_SCENES_INTRINSICS,
            resolve_depth_scale(depth_scale, None, SEVEN_SCENES_DEPTH_SCALE),
            records, f"frame-NNNNNN.color.png (or .color.jpg) / frame-NNNNNN.depth.png pairs in {path}",
        )

    def _read_depth(self, path: Path) -> np.ndarray:
        raw = read_depth_raw(path)
        depth = raw.astype(np.float32) / np.float32(self.depth_scale)
        depth[raw == SEVEN_SCENES_INVALID_DEPTH] = 0.0  # raw 0 is 0 m already: missing by convention
        return depth
