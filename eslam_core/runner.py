"""Offline runs: a data set through the SLAM system, with progress, outputs and a summary."""
from __future__ import annotations

import json
import logging
import resource
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from tqdm import tqdm

from .config import Config, save_config
from .datasets import RGBDDataset
from .evaluation.trajectory import ate
from .export import estimated_trajectory, ground_truth_trajectory, load_checkpoint, map_mesh, save_checkpoint, \
    write_trajectories
from .mesh import EmptyMeshError, save_ply
from .slam import SLAM

log = logging.getLogger("eslam")


@dataclass
class RunSummary:
    out_dir: Path
    n_frames: int
    seconds_per_frame: float
    ate_rmse_cm: Optional[float]
    peak_memory_mb: float
    mesh_path: Optional[Path]


def peak_memory_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # ru_maxrss is KiB on Linux


def apply_threads(cfg: Config) -> None:
    if cfg.run.threads > 0:
        torch.set_num_threads(cfg.run.threads)


def ate_cm(slam: SLAM) -> Optional[float]:
    gt = ground_truth_trajectory(slam)
    if gt is None or len(gt) < 3:
        return None
    return 100.0 * ate(estimated_trajectory(slam), gt, max_dt=1e-6).rmse


def run_sequence(cfg: Config, dataset: RGBDDataset, out_dir: Path, *, data_label: str = "",
                 frames: tuple = (0, None, 1), resume: Optional[Path] = None, progress: bool = True,
                 write_mesh: bool = True) -> RunSummary:
    """Process `dataset` (already subset to the frames to run) and write every output into `out_dir`."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out_dir / "config.yaml")
    torch.manual_seed(cfg.run.seed)
    apply_threads(cfg)

    if resume is not None:
        slam = load_checkpoint(resume)
        done = {r.timestamp for r in slam.records}
        todo = [i for i, t in enumerate(dataset.timestamps()) if t not in done]
        log.info("resuming from %s: %d frames done, %d to go", resume, len(slam.records), len(todo))
    else:
        slam = SLAM(cfg, dataset.intrinsics)
        todo = list(range(len(dataset)))

    bar = tqdm(todo, desc="eslam", unit="frame", disable=not progress, dynamic_ncols=True)
    start = time.perf_counter()
    for i in bar:
        res = slam.step(dataset[i])
        elapsed = time.perf_counter() - start
        bar.set_postfix(frame=res.index, fps=f"{(bar.n + 1) / elapsed:.2f}", loss=f"{res.tracking_loss:.4f}")
    seconds = time.perf_counter() - start
    n = len(todo)

    write_trajectories(slam, out_dir)
    save_checkpoint(slam, out_dir / "checkpoint.pt")
    mesh_path = None
    if write_mesh and cfg.mesh.enabled:
        try:
            mesh_path = save_ply(map_mesh(slam, cfg.mesh.resolution), out_dir / "mesh.ply")
        except EmptyMeshError as e:
            log.error("no mesh written: %s", e)

    rmse = ate_cm(slam)
    summary = {
        "data": data_label or str(dataset.root),
        "dataset_kind": dataset.kind,
        "frames": list(frames),
        "n_frames": len(slam.records),
        "frames_this_run": n,
        "seconds": seconds,
        "seconds_per_frame": seconds / max(n, 1),
        "frames_per_second": n / seconds if seconds > 0 else None,
        "peak_memory_mb": peak_memory_mb(),
        "parameter_count": slam.field.parameter_count() if slam.field is not None else 0,
        "keyframes": len(slam.keyframes),
        "keyframe_memory_mb": sum(kf.nbytes() for kf in slam.keyframes) / 2**20,
        "truncation": cfg.model.truncation,
        "bound": None if slam.bound is None else np.round(slam.bound, 4).tolist(),
        "points_outside_bound": slam.points_outside,
        "points_outside_fraction": slam.points_outside / max(slam.points_seen, 1),
        "ate_rmse_cm": rmse,
        "config_file": str(out_dir / "config.yaml"),
        "mesh": str(mesh_path) if mesh_path else None,
        "torch_threads": torch.get_num_threads(),
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return RunSummary(out_dir, n, summary["seconds_per_frame"], rmse, summary["peak_memory_mb"], mesh_path)
