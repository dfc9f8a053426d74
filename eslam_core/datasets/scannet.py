"""ScanNet scenes as exported by ScanNet's SensReader (the layout NICE-SLAM and ESLAM read).

    scene0000_00/                 (or scene0000_00/frames/, NICE-SLAM's layout, which is also accepted)
      color/N.jpg                 1296x968 colour (N.png in some exports; N may be zero-padded: 000010.jpg)
      depth/N.png                 640x480 uint16 millimetres, 0 = missing
      pose/N.txt                  4x4 camera-to-world; rows of -inf / nan mark frames the tracker lost
      intrinsic/intrinsic_depth.txt   4x4 whose top-left 3x3 is the depth camera matrix

Colour is captured by a different, larger camera; it is resized to the depth image size so that frames are
registered and `intrinsics` (those of the depth camera) hold for both. The residual offset between the two
cameras is ignored, as in ESLAM. ScanNet runs at 30 Hz and has no per-frame clock in this export, so a frame's
timestamp is its number / 30.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Optional

import numpy as np
from PIL import Image

from eslam_core.camera import Intrinsics
from eslam_core.datasets.base import (
    DatasetError,
    FrameFiles,
    RGBDDataset,
    checked_pose,
    empty_sequence_error,
    image_size,
    intrinsics_from_matrix,
    numbered_files,
    read_matrix4x4,
    read_rgb,
    require_dir,
    require_file,
    resolve_depth_scale,
)

SCANNET_DEPTH_SCALE = 1000.0
SCANNET_FRAME_RATE = 30.0

_COLOUR_NAME = re.compile(r"^(\d+)\.(?:jpg|jpeg|png)$", re.IGNORECASE)
_DEPTH_NAME = re.compile(r"^(\d+)\.png$", re.IGNORECASE)
_POSE_NAME = re.compile(r"^(\d+)\.txt$")


def find_frames_folder(path: Path) -> Path:
    """The folder holding color/ and depth/: `path` itself or its frames/ sub-folder."""
    for candidate in (path, path / "frames"):
        if (candidate / "color").is_dir() and (candidate / "depth").is_dir():
            return candidate
    raise DatasetError(
        f"no ScanNet frames in {path}: expected color/ and depth/ folders in it or in {path / 'frames'} "
        f"(export the .sens file with ScanNet's SensReader)"
    )


class ScanNetDataset(RGBDDataset):
    """A ScanNet scene; frames are the numbers present in both color/ and depth/, in numeric order.

    A frame whose pose file is missing, or marked invalid with -inf / nan, gets pose None.
    """

    kind = "scannet"

    def __init__(self, path: Path | str, intrinsics: Optional[Intrinsics] = None,
                 depth_scale: Optional[float] = None) -> None:
        path = Path(path)
        require_dir(path, "ScanNet scene folder", "pass the scene folder holding color/, depth/, pose/, intrinsic/")
        frames = find_frames_folder(path)
        colour = numbered_files(frames / "color", _COLOUR_NAME)
        depth = numbered_files(frames / "depth", _DEPTH_NAME)
        numbers = sorted(colour.keys() & depth.keys())
        looked_for = f"N.jpg / N.png pairs in {frames / 'color'} and {frames / 'depth'}"

        # Pose files by number too: exports that zero-pad image names (000010.jpg) pad pose names the same way.
        pose_files = numbered_files(frames / "pose", _POSE_NAME) if (frames / "pose").is_dir() else {}
        records = []
        for k in numbers:
            pose_file = pose_files.get(k)
            pose = None if pose_file is None else checked_pose(read_matrix4x4(pose_file, "ScanNet pose"), pose_file)
            records.append(FrameFiles(k / SCANNET_FRAME_RATE, colour[k], depth[k], pose))

        if not numbers:
            raise empty_sequence_error(frames, self.kind, looked_for)
        if intrinsics is None:
            matrix_file = require_file(
                frames / "intrinsic" / "intrinsic_depth.txt", "ScanNet depth intrinsics",
                "export it with SensReader (--export_intrinsics) or pass intrinsics (config `camera:` section)",
            )
            width, height = image_size(depth[numbers[0]], "depth image")
            intrinsics = intrinsics_from_matrix(
                read_matrix4x4(matrix_file, "ScanNet intrinsic matrix"), width, height, matrix_file
            )
        self._setup(
            frames, path.resolve().name, intrinsics,
            resolve_depth_scale(depth_scale, None, SCANNET_DEPTH_SCALE),
            records, looked_for,
        )

    def _read_rgb(self, path: Path) -> np.ndarray:
        """Colour resized (bilinear) to the depth image size, so that it is registered with the intrinsics."""
        rgb = read_rgb(path)
        size = (self.intrinsics.width, self.intrinsics.height)
        if (rgb.shape[1], rgb.shape[0]) == size:
            return rgb
        return np.asarray(Image.fromarray(rgb).resize(size, Image.Resampling.BILINEAR), dtype=np.uint8)
