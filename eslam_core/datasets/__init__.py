"""RGB-D data set readers: TUM RGB-D, ICL-NUIM (TUM layout), Replica, ScanNet and 7-Scenes.

    dataset = open_dataset("/data/replica/office0")      # format detected from the folder's contents
    frame = dataset[0]                                   # Frame: rgb uint8, depth float32 metres, pose or None
    every_other = dataset.subset(stride=2)

Every reader returns registered colour and depth of the same size, `intrinsics` for that size, and ground-truth
poses camera-to-world in OpenCV axes (converted where a data set uses other axes).
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from eslam_core.camera import Intrinsics
from eslam_core.datasets.base import DatasetError, FrameFiles, RGBDDataset
from eslam_core.datasets.replica import ReplicaDataset
from eslam_core.datasets.scannet import ScanNetDataset
from eslam_core.datasets.sevenscenes import SevenScenesDataset, has_frames as has_7scenes_frames
from eslam_core.datasets.tum import ICLNUIMDataset, TUMDataset

__all__ = [
    "DatasetError",
    "FrameFiles",
    "ICLNUIMDataset",
    "RGBDDataset",
    "ReplicaDataset",
    "ScanNetDataset",
    "SevenScenesDataset",
    "TUMDataset",
    "DATASET_KINDS",
    "detect_kind",
    "open_dataset",
]

DATASET_KINDS: dict[str, type[RGBDDataset]] = {
    reader.kind: reader
    for reader in (TUMDataset, ICLNUIMDataset, ReplicaDataset, ScanNetDataset, SevenScenesDataset)
}


def _has_dirs(folder: Path, *names: str) -> bool:
    return all((folder / name).is_dir() for name in names)


def _looks_like_replica(folder: Path) -> bool:
    if (folder / "cam_params.json").is_file():
        return True
    scene_folders = [folder, *(child for child in folder.iterdir() if child.is_dir())]
    return any((scene / "results").is_dir() and (scene / "traj.txt").is_file() for scene in scene_folders)


def detect_kind(path: Path | str) -> str:
    """The format of a data set folder, from the files it holds. ICL-NUIM looks like TUM: it is never detected.

    Checked in this order: replica (cam_params.json, or results/ + traj.txt here or in a sub-folder), scannet
    (color/ and depth/ folders, here or in frames/), 7scenes (frame-*.color.png or .jpg, here or in seq-*/), tum
    (rgb.txt + depth.txt, or associations.txt).
    """
    folder = Path(path)
    if not folder.is_dir():
        raise DatasetError(f"data set folder {folder} not found (or not a folder); check the path")
    if _looks_like_replica(folder):
        return "replica"
    if _has_dirs(folder, "color", "depth") or _has_dirs(folder / "frames", "color", "depth"):
        return "scannet"
    if has_7scenes_frames(folder) or any(has_7scenes_frames(seq) for seq in folder.glob("seq-*")):
        return "7scenes"
    if ((folder / "rgb.txt").is_file() and (folder / "depth.txt").is_file()) or (folder / "associations.txt").is_file():
        return "tum"
    raise DatasetError(
        f"cannot tell which data set {folder} is: looked for cam_params.json or results/ + traj.txt (replica), "
        f"color/ + depth/ folders (scannet), frame-*.color.png / .jpg (7scenes), rgb.txt + depth.txt or "
        f"associations.txt (tum); pass kind= one of {', '.join(DATASET_KINDS)} (ICL-NUIM needs kind='icl')"
    )


def open_dataset(
    path: Path | str,
    kind: str = "auto",
    *,
    intrinsics: Optional[Intrinsics] = None,
    depth_scale: Optional[float] = None,
    register_colour: bool = True,
) -> RGBDDataset:
    """Open an RGB-D sequence. `intrinsics` / `depth_scale` override what the reader finds in files or defaults;
    `register_colour` False keeps a data set's unregistered colour as shipped (see RGBDDataset.colour_intrinsics)."""
    chosen = kind.strip().lower()
    if chosen == "auto":
        chosen = detect_kind(path)
    reader = DATASET_KINDS.get(chosen)
    if reader is None:
        raise DatasetError(f"unknown data set kind {kind!r}; use 'auto' or one of {', '.join(DATASET_KINDS)}")
    if depth_scale is not None and not float(depth_scale) > 0:
        raise DatasetError(f"depth_scale must be a positive number of raw depth units per metre, got {depth_scale}")
    dataset = reader(path, intrinsics=intrinsics, depth_scale=depth_scale)
    dataset.register_colour = register_colour
    return dataset
