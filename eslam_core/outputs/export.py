"""What a run leaves behind: checkpoint, trajectory (TUM format) and mesh of the map."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import trimesh

from eslam_core.outputs.culling import visible_mask
from eslam_core.datasets.tum import write_tum
from eslam_core.trajectory import Trajectory
from eslam_core.mapping.scene_map import SceneMap, surface_points
from eslam_core.atomic import atomic_output, write_atomic
from eslam_core.outputs.mesh import EmptyMeshError, MeshSettings, extract_mesh
from eslam_core.map_file import CheckpointError, read_checkpoint
from eslam_core.slam import CHECKPOINT_VERSION, SLAM
from eslam_core.tracking.information import PoseCovariance


def save_checkpoint(slam: SLAM, path: Path) -> Path:
    """Write the SLAM state; a failed save (e.g. a full disk) is one OutputWriteError line and leaves an older
    checkpoint of the same name as it was."""
    path = Path(path)
    state = slam.state_dict()
    with atomic_output(path, size_hint=tensor_bytes(state)) as tmp:
        torch.save(state, tmp)
    return path


def tensor_bytes(value) -> int:
    """About the size torch.save gives `value`: its tensors' bytes (the pickle around them is small)."""
    if isinstance(value, torch.Tensor):
        return value.numel() * value.element_size()
    if isinstance(value, dict):
        return sum(tensor_bytes(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return sum(tensor_bytes(v) for v in value)
    return 0


def load_checkpoint(path: Path, mode: str | None = None) -> SLAM:
    """The SLAM state saved in a checkpoint, read safely (map_file.py): errors are one CheckpointError line.
    `mode` ("slam" or "localization") replaces the saved run.mode."""
    state = read_checkpoint(path, CHECKPOINT_VERSION)
    if mode is not None:
        state["config"]["run"]["mode"] = mode
    try:
        return SLAM.from_state_dict(state)
    except (KeyError, IndexError, TypeError, ValueError, RuntimeError, AttributeError) as e:
        raise CheckpointError(f"{path} is damaged (incomplete map: {type(e).__name__} {e}); re-run `eslam run` "
                              f"to make a new one") from None


def estimated_trajectory(slam: SLAM) -> Trajectory:
    return Trajectory(slam.trajectory.timestamps(), slam.trajectory.poses())


def ground_truth_trajectory(slam: SLAM) -> Trajectory | None:
    known = [(r.timestamp, r.gt_pose) for r in slam.trajectory.records if r.gt_pose is not None]
    if not known:
        return None
    return Trajectory(np.array([t for t, _ in known]), np.stack([p for _, p in known]))


def save_trajectory(trajectory: Trajectory, path: Path) -> Path:
    """A TUM trajectory file, written whole or not at all (atomic_output)."""
    path = Path(path)
    with atomic_output(path) as tmp:
        write_tum(tmp, trajectory)
    return path


def write_trajectories(slam: SLAM, out_dir: Path) -> Path:
    """trajectory.txt (returned), pose_quality.csv and, where the frames had one, groundtruth.txt."""
    path = save_trajectory(estimated_trajectory(slam), out_dir / "trajectory.txt")
    write_atomic(out_dir / "pose_quality.csv", tracking_table(slam.trajectory))
    gt = ground_truth_trajectory(slam)
    if gt is not None:
        save_trajectory(gt, out_dir / "groundtruth.txt")
    return path


AXES = ("x", "y", "z", "roll", "pitch", "yaw")
UPPER = np.triu_indices(6)


def tracking_table(trajectory) -> str:
    """How far each frame's pose can be trusted, one line per frame: its quality, whether it was lost or degraded,
    its covariance's largest position (m) and rotation (deg) standard deviations and the covariance itself (upper
    triangle, REP 103 order, m and rad; empty where not measured)."""
    pairs = [f"cov_{AXES[i]}_{AXES[j]}" for i, j in zip(*UPPER)]
    lines = [",".join(["timestamp", "quality", "lost", "degraded", "sigma_m", "sigma_deg"] + pairs)]
    for r in trajectory.records:
        measured = [""] * (2 + len(pairs))
        if r.covariance is not None:
            c = PoseCovariance(r.covariance)
            measured = [f"{c.sigma_m:.5f}", f"{c.sigma_deg:.3f}"] + [f"{v:.4g}" for v in r.covariance[UPPER]]
        lines.append(",".join([f"{r.timestamp:.6f}", f"{r.quality:.3f}", str(int(r.lost)), str(int(r.degraded))]
                              + measured))
    return "\n".join(lines) + "\n"


def tracking_summary(trajectory) -> dict:
    """summary.json's share of pose_quality.csv."""
    records = trajectory.records
    sigmas = [PoseCovariance(r.covariance).sigma_m for r in records if r.covariance is not None]
    return {"frames_lost": int(records.column("lost").sum()), "frames_degraded": int(records.column("degraded").sum()),
            "sigma_m_median": float(np.median(sigmas)) if sigmas else None}


def observed_bound(scene: SceneMap, dirs_cam: torch.Tensor, width: int, margin: float) -> np.ndarray:
    """Box around what a map's keyframes observed (plus a margin), inside its bound, in its frame: what is worth
    meshing."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for kf in scene.keyframes:
        pts = surface_points(dirs_cam, kf, width, stride=1)
        if len(pts):
            lo = np.minimum(lo, pts.amin(0).numpy())
            hi = np.maximum(hi, pts.amax(0).numpy())
    extent = scene.extent
    if not np.all(np.isfinite(lo)):
        return extent
    return np.stack([np.maximum(lo - margin, extent[0]), np.minimum(hi + margin, extent[1])])


def submap_mesh(slam: SLAM, scene: SceneMap, resolution: float) -> trimesh.Trimesh:
    """Marching cubes on one map's decoded SDF over its observed region, culled to what its keyframes saw, in the
    world frame (a submap's mesh moved by its anchor)."""
    T = slam.cfg.model.truncation
    keyframes, (h, w) = scene.keyframes, (slam.intr.height, slam.intr.width)
    poses = torch.stack([kf.pose for kf in keyframes]).double().numpy()
    depths = torch.stack([kf.frame_depth_image(h, w) for kf in keyframes]).numpy()

    def visible(points: np.ndarray) -> np.ndarray:
        return visible_mask(points, poses, slam.intr, depths, T)

    field = scene.field.eval()
    with torch.no_grad():
        mesh = extract_mesh(field.sdf, field.color, observed_bound(scene, slam.dirs_cam, slam.intr.width, 2 * T),
                            MeshSettings(resolution=resolution, truncation=T), visible_fn=visible)
    if scene.anchor is not None:
        mesh.apply_transform(scene.anchor)
    return mesh


def map_mesh(slam: SLAM, resolution: float) -> trimesh.Trimesh:
    """The mesh of every submap (the map, with one), in the world frame."""
    if slam.map.field is None:
        raise CheckpointError("the map is empty: no frame has been processed")
    meshes = []
    for scene in slam.atlas.submaps:
        try:
            meshes.append(submap_mesh(slam, scene, resolution))
        except EmptyMeshError:
            if len(slam.atlas.submaps) == 1:
                raise
    if not meshes:
        raise EmptyMeshError("no submap has a surface to mesh")
    return meshes[0] if len(meshes) == 1 else trimesh.util.concatenate(meshes)
