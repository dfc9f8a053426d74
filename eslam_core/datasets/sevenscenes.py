"""Microsoft 7-Scenes sequences (one `seq-XX/` folder of a scene such as `chess/`).

    seq-01/frame-000000.color.png   640x480 colour
    seq-01/frame-000000.depth.png   640x480 uint16 millimetres, 65535 = no measurement
    seq-01/frame-000000.pose.txt    4x4 camera-to-world (from KinectFusion)

7-Scenes colour and depth come from the Kinect's two cameras and are NOT registered: a colour pixel and the depth
pixel at the same coordinates see slightly different points (a few pixels apart, more at close range). This reader
does not correct it (ESLAM does not either): geometry is right, colour is somewhat blurred onto it. The default
intrinsics are the nominal ones the data set documents for depth. Frames are recorded at 30 Hz without
timestamps, so a frame's timestamp is its number (the NNNNNN in its file names) / 30.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Optional

import numpy as np

from eslam_core.camera import Intrinsics
from eslam_core.datasets.base import (
    DatasetError,
    FrameRecord,
    RGBDDataset,
    checked_pose,
    numbered_files,
    read_depth_raw,
    read_matrix4x4,
    require_dir,
    resolve_depth_scale,
)

SEVEN_SCENES_INTRINSICS = Intrinsics(640, 480, fx=585.0, fy=585.0, cx=320.0, cy=240.0)
SEVEN_SCENES_DEPTH_SCALE = 1000.0
SEVEN_SCENES_FRAME_RATE = 30.0
SEVEN_SCENES_INVALID_DEPTH = 65535  # the raw value marking pixels without a measurement

_COLOUR_NAME = re.compile(r"^frame-(\d+)\.color\.png$")
_DEPTH_NAME = re.compile(r"^frame-(\d+)\.depth\.png$")


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

    A frame without a pose file, or with a non-finite pose, gets pose None.
    """

    kind = "7scenes"

    def __init__(self, path: Path | str, intrinsics: Optional[Intrinsics] = None,
                 depth_scale: Optional[float] = None) -> None:
        path = Path(path)
        require_dir(path, "7-Scenes sequence folder", "pass a seq-XX folder holding frame-NNNNNN.color.png files")
        colour = numbered_files(path, _COLOUR_NAME)
        depth = numbered_files(path, _DEPTH_NAME)
        if not colour and not depth:
            _reject_scene_folder(path)
        records = []
        for k in sorted(colour.keys() & depth.keys()):
            pose_file = path / f"frame-{k:06d}.pose.txt"
            pose = checked_pose(read_matrix4x4(pose_file, "7-Scenes pose"), pose_file) if pose_file.is_file() else None
            records.append(FrameRecord(k / SEVEN_SCENES_FRAME_RATE, colour[k], depth[k], pose))
        resolved = path.resolve()
        self._setup(
            path, f"{resolved.parent.name}-{resolved.name}", intrinsics or SEVEN_SCENES_INTRINSICS,
            resolve_depth_scale(depth_scale, None, SEVEN_SCENES_DEPTH_SCALE),
            records, f"frame-NNNNNN.color.png / frame-NNNNNN.depth.png pairs in {path}",
        )

    def _read_depth(self, path: Path) -> np.ndarray:
        raw = read_depth_raw(path)
        depth = raw.astype(np.float32) / np.float32(self.depth_scale)
        depth[raw == SEVEN_SCENES_INVALID_DEPTH] = 0.0
        return depth
