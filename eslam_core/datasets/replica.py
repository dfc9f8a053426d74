"""Replica sequences in the layout NICE-SLAM and ESLAM distribute.

    Replica/                      <- the root: cam_params.json, one folder per scene (and meshes)
      cam_params.json             {"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}}
      office0_mesh.ply            ground-truth mesh (optional)
      office0/                    <- the scene folder
        results/frame000000.jpg   colour
        results/depth000000.png   uint16 depth, metres = value / scale
        traj.txt                  line i = row-major 4x4 camera-to-world of frame i (OpenCV axes)

The images are rendered, so colour and depth are registered and undistorted; there is no clock, so a frame's
timestamp is its frame number.
"""
from __future__ import annotations

import json
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
    numbered_files,
    parse_floats,
    read_text_rows,
    require_dir,
    resolve_depth_scale,
)

# NICE-SLAM's configs/Replica/replica.yaml, used when no cam_params.json is found.
REPLICA_INTRINSICS = Intrinsics(1200, 680, fx=600.0, fy=600.0, cx=599.5, cy=339.5)
REPLICA_DEPTH_SCALE = 6553.5

_COLOUR_NAME = re.compile(r"^frame(\d+)\.(?:jpg|jpeg|png)$", re.IGNORECASE)
_DEPTH_NAME = re.compile(r"^depth(\d+)\.png$", re.IGNORECASE)


def find_scene_folder(path: Path) -> Path:
    """The scene folder (the one holding results/) given either it or the Replica root that contains it."""
    if (path / "results").is_dir():
        return path
    scenes = sorted(child for child in path.iterdir() if (child / "results").is_dir()) if path.is_dir() else []
    if len(scenes) == 1:
        return scenes[0]
    if not scenes:
        raise DatasetError(
            f"no Replica scene in {path}: expected a results/ folder in it or in one of its sub-folders "
            f"(e.g. {path / 'office0' / 'results'})"
        )
    raise DatasetError(
        f"{path} holds several Replica scenes ({', '.join(s.name for s in scenes)}); pass one scene folder, "
        f"e.g. {scenes[0]}"
    )


def read_cam_params(path: Path) -> tuple[Intrinsics, float]:
    """Intrinsics and depth scale of a NICE-SLAM `cam_params.json`."""
    try:
        camera = json.loads(path.read_text())["camera"]
        intrinsics = Intrinsics(
            int(camera["w"]), int(camera["h"]),
            float(camera["fx"]), float(camera["fy"]), float(camera["cx"]), float(camera["cy"]),
        )
        return intrinsics, float(camera["scale"])
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise DatasetError(f"cannot read camera file {path} ({err}); fix the JSON or delete the file") from None
    except (KeyError, TypeError, ValueError) as err:
        raise DatasetError(
            f"camera file {path} is missing or has an invalid entry ({err}); it needs "
            f'{{"camera": {{"w", "h", "fx", "fy", "cx", "cy", "scale"}}}}'
        ) from None


def read_replica_trajectory(path: Path) -> list[Optional[np.ndarray]]:
    """One 4x4 camera-to-world pose per line (16 numbers, row-major)."""
    rows = read_text_rows(path, 16, "Replica trajectory (16 numbers, a row-major 4x4 pose, per line)")
    return [checked_pose(parse_floats(fields, path, n).reshape(4, 4), path, n) for n, fields in rows]


class ReplicaDataset(RGBDDataset):
    """A Replica scene (NICE-SLAM layout); `path` may be the scene folder or the root holding cam_params.json.

    Frames are the frame/depth image pairs present in results/, in frame-number order; frame number k gets
    line k of traj.txt as its pose (None when traj.txt is absent or shorter).
    """

    kind = "replica"

    def __init__(self, path: Path | str, intrinsics: Optional[Intrinsics] = None,
                 depth_scale: Optional[float] = None) -> None:
        path = Path(path)
        require_dir(path, "Replica folder", "pass the scene folder (holding results/ and traj.txt) or its parent")
        scene = find_scene_folder(path)
        results = scene / "results"

        found_intrinsics, found_scale = REPLICA_INTRINSICS, None
        for candidate in (scene / "cam_params.json", scene.parent / "cam_params.json"):
            if candidate.is_file():
                found_intrinsics, found_scale = read_cam_params(candidate)
                break

        trajectory = scene / "traj.txt"
        poses = read_replica_trajectory(trajectory) if trajectory.is_file() else []

        colour = numbered_files(results, _COLOUR_NAME)
        depth = numbered_files(results, _DEPTH_NAME)
        records = [
            FrameFiles(float(k), colour[k], depth[k], poses[k] if k < len(poses) else None)
            for k in sorted(colour.keys() & depth.keys())
        ]
        self._setup(
            scene, scene.name, intrinsics or found_intrinsics,
            resolve_depth_scale(depth_scale, found_scale, REPLICA_DEPTH_SCALE),
            records, f"frameNNNNNN.jpg / depthNNNNNN.png pairs in {results}",
        )

    @property
    def mesh_path(self) -> Optional[Path]:
        """The scene's ground-truth mesh (`<scene>_mesh.ply` next to the scene folder or inside it), if present."""
        for candidate in (self.root.parent / f"{self.name}_mesh.ply", self.root / f"{self.name}_mesh.ply"):
            if candidate.is_file():
                return candidate
        return None
