"""`eslam demo`: the embedded synthetic room, generated once and cached, run and scored."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import numpy as np
import trimesh

from eslam_core.config import Config
from eslam_core.outputs.culling import cull_mesh
from eslam_core.datasets import RGBDDataset, open_dataset
from eslam_core.evaluation.reconstruction import reconstruction_metrics
from eslam_core.runner import RunSummary, run_sequence
from eslam_core.datasets.synthetic import ensure_scene


def default_cache() -> Path:
    return Path(os.environ.get("ESLAM_CACHE", Path.home() / ".cache" / "eslam")) / "scenes"


def parse_size(size: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise ValueError(f"--size expects WxH such as 320x240, got {size!r}") from None
    return w, h


def mesh_scores(rec_path: Path, gt_path: Path, ds: RGBDDataset, truncation: float, n_points: int = 200_000):
    """Accuracy / completion of the run's mesh against the true mesh, both culled to what the cameras saw."""
    step = max(1, len(ds) // 100)
    frames = [ds[i] for i in range(0, len(ds), step)]
    poses = np.stack([f.pose for f in frames])
    depths = np.stack([f.depth for f in frames])
    gt = trimesh.load(gt_path, process=False)
    # Culling keeps whole faces; the true mesh's large faces must be split first or partly seen walls vanish.
    gt = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(gt.vertices, gt.faces, max_edge=0.02), process=False)
    gt = cull_mesh(gt, poses, ds.intrinsics, depths, truncation)
    rec = cull_mesh(trimesh.load(rec_path, process=False), poses, ds.intrinsics, depths, truncation)
    return reconstruction_metrics(rec, gt, n_points=n_points)


def run_demo(cfg: Config, out: Path, n_frames: int = 60, size: str = "320x240", cache: Optional[Path] = None,
             progress: bool = True) -> tuple[RunSummary, object]:
    w, h = parse_size(size)
    scene = ensure_scene(cache or default_cache(), n_frames=n_frames, width=w, height=h, seed=cfg.run.seed)
    ds = open_dataset(scene, "tum")
    summary = run_sequence(cfg, ds, out, data_label=str(scene), progress=progress)
    print(f"demo: {summary.n_frames} frames of the synthetic room ({w}x{h}), {summary.seconds_per_frame:.2f} s/frame,"
          f" peak memory {summary.peak_memory_mb:.0f} MB")
    print(f"  ATE RMSE: {summary.ate_rmse_cm:.2f} cm")
    scores = None
    if summary.mesh_path is not None:
        scores = mesh_scores(summary.mesh_path, scene / "mesh.ply", ds, cfg.model.truncation)
        print(f"  mesh accuracy {100 * scores.accuracy:.2f} cm, completion {100 * scores.completion:.2f} cm, "
              f"completion ratio {100 * scores.completion_ratio:.1f} %")
    print(f"  outputs in {summary.out_dir}")
    return summary, scores
