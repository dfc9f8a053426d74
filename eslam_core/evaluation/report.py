"""Evaluate a finished run directory (`eslam run --out DIR`) and write `report.json` / `report.md`.

What is evaluated depends on what the run and the data set provide:
- trajectory (needs `groundtruth.txt`): ATE after rigid alignment, RPE per frame and per metre;
- depth consistency (needs the data set's depth images, not ground truth): the frames' depths warped into each
  other with the estimated poses (`consistency.py`), and with the reference poses where the data set has them;
- reconstruction (needs `mesh.ply` and a ground-truth mesh): both meshes culled to what the run's cameras observed
  (ground-truth poses, sensor depths, the run's truncation), then accuracy / completion / completion ratio /
  precision / recall / F-score, and depth L1 over random views;
- speed and memory, copied from `summary.json`; the configuration, from `config.yaml`.
Anything missing is listed under "skipped" with the reason, never silently dropped. Distances in the report are cm.
"""
from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator, Optional, Sequence, Union

import numpy as np
import trimesh
import yaml

from eslam_core.camera import Intrinsics
from eslam_core.outputs.culling import keep_visible_faces, visible_mask
from eslam_core.mapping.consistency import (
    FAR_FRAMES,
    NEAR_FRAMES,
    ConsistencyResult,
    choose_pairs,
    sequence_consistency,
)
from eslam_core.evaluation.depth_l1 import depth_l1
from eslam_core.evaluation.reconstruction import check_mesh, icp_align, load_mesh, reconstruction_metrics
from eslam_core.datasets.tum import read_tum
from eslam_core.evaluation.trajectory_error import associate, ate, path_length, rpe
from eslam_core.trajectory import Trajectory

log = logging.getLogger(__name__)

PathLike = Union[str, Path]
ALIGN_CHOICES = ("none", "icp")
CAMERAS_PER_CHUNK = 16  # depth images held in memory at once while culling
CONSISTENCY_FRAMES = 100  # frames (evenly spread) whose depths the consistency score warps into each other


class RunDirectoryError(ValueError):
    """A run directory that cannot be evaluated (missing files, unreadable summary, unreachable data set)."""


# ---------------------------------------------------------------------------------------------------------------
# Reading the run directory


@dataclass(frozen=True)
class RunFiles:
    run_dir: Path
    summary: dict
    trajectory: Path
    groundtruth: Optional[Path]
    mesh: Optional[Path]
    config: Optional[Path]
    pose_quality: Optional[Path] = None  # per frame: quality, lost, degraded, covariance (outputs/export.py)


def read_run(run_dir: PathLike) -> RunFiles:
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunDirectoryError(f"run directory not found: {run_dir} (the --out folder of `eslam run`)")
    summary_path = run_dir / "summary.json"
    if not summary_path.is_file():
        raise RunDirectoryError(f"{run_dir} has no summary.json: is it the --out folder of a finished `eslam run`?")
    try:
        summary = json.loads(summary_path.read_text())
    except json.JSONDecodeError as error:
        raise RunDirectoryError(
            f"{summary_path} is not valid JSON ({error}): the run may have been interrupted"
        ) from None
    trajectory = run_dir / "trajectory.txt"
    if not trajectory.is_file():
        raise RunDirectoryError(f"{run_dir} has no trajectory.txt: the run did not finish writing its results")

    def optional(name: str) -> Optional[Path]:
        path = run_dir / name
        return path if path.is_file() else None

    return RunFiles(
        run_dir, summary, trajectory, optional("groundtruth.txt"), optional("mesh.ply"), optional("config.yaml"),
        optional("pose_quality.csv"),
    )


def read_pose_quality(path: Path) -> dict[str, np.ndarray]:
    """pose_quality.csv's columns by name (NaN where a frame has no covariance)."""
    lines = path.read_text().splitlines()
    if not lines or not lines[0].startswith("timestamp,"):
        raise RunDirectoryError(f"{path} has no 'timestamp,...' header: not a pose_quality.csv of `eslam run`")
    names = lines[0].split(",")
    rows = [[float(v) if v else np.nan for v in line.split(",")] for line in lines[1:] if line]
    table = np.array(rows, dtype=np.float64).reshape(len(rows), len(names))
    return {name: table[:, i] for i, name in enumerate(names)}


def _covariance_section(quality: dict[str, np.ndarray], result) -> tuple[dict, np.ndarray]:
    """How the predicted position sigma (sqrt of the covariance's position trace) compares with the errors against
    the ground truth, and each matched pose's sigma (NaN where not measured)."""
    sigma = np.sqrt(quality["cov_x_x"] + quality["cov_y_y"] + quality["cov_z_z"])
    matched = associate(quality["timestamp"], result.timestamps, 0.02)
    per_pose = np.full(len(result.errors), np.nan)
    per_pose[matched[:, 1]] = sigma[matched[:, 0]]
    ratio = result.errors / per_pose
    ratio = ratio[np.isfinite(ratio)]
    return {
        "frames_degraded": int(np.nansum(quality["degraded"])),
        "frames_lost": int(np.nansum(quality["lost"])),
        "sigma_median_cm": float(100 * np.nanmedian(sigma)) if np.isfinite(sigma).any() else None,
        "error_over_sigma_median": float(np.median(ratio)) if len(ratio) else None,
        "within_2_sigma_percent": float(100 * np.mean(ratio <= 2.0)) if len(ratio) else None,
    }, per_pose


def _read_config(path: Optional[Path]) -> Optional[dict]:
    if path is None:
        return None
    try:
        return yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise RunDirectoryError(
            f"{path} is not valid YAML ({error}): restore it from the config the run used"
        ) from None


def find_gt_mesh(data_path: Path) -> Optional[Path]:
    """The ground-truth mesh next to a data set: NICE-SLAM layout (Replica/office0 -> Replica/office0_mesh.ply, or a
    single <scene>_mesh.ply inside the folder given), or `mesh.ply` inside it (the embedded synthetic room)."""
    for candidate in (data_path.parent / f"{data_path.name}_mesh.ply", data_path / f"{data_path.name}_mesh.ply",
                      data_path / "mesh.ply"):
        if candidate.is_file():
            return candidate
    inside = sorted(data_path.glob("*_mesh.ply")) if data_path.is_dir() else []
    return inside[0] if len(inside) == 1 else None


# ---------------------------------------------------------------------------------------------------------------
# Trajectory section


def _trajectory_section(est: Trajectory, gt: Trajectory) -> tuple[dict, Any]:
    result = ate(est, gt, align=True)
    section: dict[str, Any] = {
        "matched_poses": result.n,
        "estimated_poses": len(est),
        "ate_rmse_cm": 100 * result.rmse,
        "ate_mean_cm": 100 * result.mean,
        "ate_median_cm": 100 * result.median,
        "ate_max_cm": 100 * result.max,
        "ate_std_cm": 100 * result.std,
        "alignment": "rigid (Umeyama rotation + translation, no scale)",
        "gt_path_length_m": float(path_length(result.gt_positions)[-1]),
    }
    per_frame = rpe(est, gt, delta=1, unit="frames")
    section["rpe_per_frame"] = _rpe_dict(per_frame)
    if section["gt_path_length_m"] >= 1.0:
        section["rpe_per_metre"] = _rpe_dict(rpe(est, gt, delta=1.0, unit="metres"))
    else:
        section["rpe_per_metre"] = None
        section["rpe_per_metre_note"] = "ground-truth path shorter than 1 m"
    return section, result


def _rpe_dict(result) -> dict:
    return {
        "pairs": result.n,
        "trans_rmse_cm": 100 * result.trans_rmse,
        "trans_mean_cm": 100 * result.trans_mean,
        "rot_rmse_deg": result.rot_rmse,
        "rot_mean_deg": result.rot_mean,
    }


# ---------------------------------------------------------------------------------------------------------------
# Culling cameras: the run's frames, reloaded from the data set


@dataclass(frozen=True)
class ObservingCameras:
    intrinsics: Intrinsics
    dataset: Any  # eslam_core.datasets.RGBDDataset, already restricted to the run's frames
    indices: tuple[int, ...]  # frames of `dataset` used as culling cameras
    estimate: Trajectory  # fallback pose for frames without ground truth

    def chunks(self, size: int = CAMERAS_PER_CHUNK) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """(poses (k, 4, 4), depths (k, H, W)) of `size` cameras at a time, so memory stays bounded."""
        for start in range(0, len(self.indices), size):
            poses, depths = [], []
            for index in self.indices[start : start + size]:
                frame = self.dataset[index]
                pose = frame.pose if frame.pose is not None else self._estimated_pose(frame.timestamp)
                if pose is None or not np.isfinite(pose).all():
                    continue
                poses.append(pose)
                depths.append(np.asarray(frame.depth, dtype=np.float32))
            if poses:
                yield np.stack(poses), np.stack(depths)

    def _estimated_pose(self, timestamp: float) -> Optional[np.ndarray]:
        nearest = int(np.argmin(np.abs(self.estimate.timestamps - timestamp)))
        if abs(self.estimate.timestamps[nearest] - timestamp) > 0.02:
            return None
        return self.estimate.poses[nearest]


def _camera_overrides(config: Optional[dict]) -> dict:
    """The run's camera overrides (config `camera:` section) that change how frames are read: depth scale and
    intrinsics. Image resizing and depth cut-off are deliberately not applied: culling uses the sensor depth."""
    camera = (config or {}).get("camera") or {}
    overrides: dict[str, Any] = {}
    if camera.get("depth_scale"):
        overrides["depth_scale"] = float(camera["depth_scale"])
    keys = ("width", "height", "fx", "fy", "cx", "cy")
    if all(camera.get(key) is not None for key in keys):
        overrides["intrinsics"] = Intrinsics(**{key: camera[key] for key in keys})
    return overrides


def data_set_path(summary: dict, data: Optional[PathLike]) -> Optional[Path]:
    """Where the run's data set is (`data` overrides summary.json's), None if it is not there."""
    recorded = data if data is not None else summary.get("data")
    return Path(recorded) if recorded and Path(recorded).exists() else None


def open_run_dataset(summary: dict, data: Optional[PathLike], config: Optional[dict], purpose: str):
    """The run's frames of its data set (same reader, camera overrides and frame range as the run)."""
    data_path = data_set_path(summary, data)
    if data_path is None:
        recorded = data if data is not None else summary.get("data")
        raise RunDirectoryError(
            f"data set not found at {recorded or '(summary.json has no data path)'}: {purpose} needs the run's "
            "depth images; pass the data set location with --data"
        )
    try:
        from eslam_core.datasets import open_dataset
    except ImportError as error:
        raise RunDirectoryError(
            f"cannot load data sets ({error}): eslam_core.datasets is required for {purpose}"
        ) from None
    dataset = open_dataset(data_path, summary.get("dataset_kind") or "auto", **_camera_overrides(config))
    start, stop, stride = (list(summary.get("frames") or [0, None, 1]) + [None, None, None])[:3]
    dataset = dataset.subset(start or 0, stop, stride or 1)
    if len(dataset) == 0:
        raise RunDirectoryError(f"the run's frames {summary.get('frames')} select no frame of {data_path}")
    return dataset


def observing_cameras(
    summary: dict, data: Optional[PathLike], estimate: Trajectory, max_cameras: int, config: Optional[dict] = None
) -> ObservingCameras:
    """The run's frames (every frame, or a stride keeping at most `max_cameras`) with their sensor depth."""
    dataset = open_run_dataset(summary, data, config, "culling")
    n = len(dataset)
    camera_stride = math.ceil(n / max_cameras)
    return ObservingCameras(dataset.intrinsics, dataset, tuple(range(0, n, camera_stride)), estimate)


def cull_to_observed(
    meshes: Sequence[trimesh.Trimesh], cameras: ObservingCameras, truncation: float
) -> tuple[list[trimesh.Trimesh], int]:
    """Cull all `meshes` with the same cameras in one pass over the frames; returns the meshes and camera count."""
    points = np.concatenate([np.asarray(mesh.vertices) for mesh in meshes])
    visible = np.zeros(len(points), dtype=bool)
    n_cameras = 0
    for poses, depths in cameras.chunks():
        pending = np.flatnonzero(~visible)
        visible[pending] = visible_mask(points[pending], poses, cameras.intrinsics, depths, truncation)
        n_cameras += len(poses)
    if n_cameras == 0:
        raise RunDirectoryError("no frame of the run has a pose to cull with (neither ground truth nor estimate)")
    culled, offset = [], 0
    for mesh in meshes:
        culled.append(keep_visible_faces(mesh, visible[offset : offset + len(mesh.vertices)]))
        offset += len(mesh.vertices)
    return culled, n_cameras


# ---------------------------------------------------------------------------------------------------------------
# Depth consistency section


def _consistency_section(dataset, estimate: Trajectory, max_frames: int) -> tuple[
        Optional[dict], Optional[ConsistencyResult], Optional[ConsistencyResult]]:
    """Depth consistency of the estimated poses and, where the data set has them, of the reference poses; Nones
    when no two frames see the same surface (a run of a few frames).

    Frames: the run's frames that have an estimated pose, at most `max_frames` evenly spread. Pairs are chosen once,
    by view overlap under the estimated poses (what a user without ground truth has), and both sets of poses are
    scored on the same pairs; pairs whose frames lack a reference pose are left out of both.
    """
    matches = associate(dataset.timestamps(), estimate.timestamps, 0.02)  # (run frame, estimated pose)
    step = max(1, math.ceil(len(matches) / max_frames))
    chosen = matches[::step]
    frames = [dataset[int(k)] for k in chosen[:, 0]]
    depths = [np.asarray(frame.depth, dtype=np.float32) for frame in frames]
    numbers = [int(k) for k in chosen[:, 0]]
    estimated = estimate.poses[chosen[:, 1]]
    reference = np.stack([frame.pose if frame.pose is not None else np.full((4, 4), np.nan) for frame in frames])
    has_reference = np.isfinite(reference).all(axis=(1, 2))
    pairs = choose_pairs(depths, estimated, numbers, dataset.intrinsics)
    if has_reference.any():
        pairs = [(k, m, kind) for k, m, kind in pairs if has_reference[k] and has_reference[m]]
    if not pairs:
        return None, None, None
    options = dict(frame_numbers=numbers)
    of_estimate = sequence_consistency(depths, estimated, pairs, dataset.intrinsics, **options)
    of_reference = (sequence_consistency(depths, reference, pairs, dataset.intrinsics, **options)
                    if has_reference.any() else None)
    section = {
        "frames": len(frames),
        "frame_step": step,
        "pairs_chosen_by": f"view overlap under the estimated poses: each frame with the first frame {NEAR_FRAMES} "
                           f"or more on (near) and the latest frame {FAR_FRAMES} or more on seeing the same "
                           f"surface (far)",
        "estimate": of_estimate.summary(),
        "reference": None if of_reference is None else of_reference.summary(),
    }
    return section, of_estimate, of_reference


def _consistency_plot(of_estimate: ConsistencyResult, of_reference: Optional[ConsistencyResult],
                      run_dir: Path) -> dict[str, str]:
    from eslam_core.evaluation import plots as figures

    path = figures.plot_consistency(of_estimate.pairs, None if of_reference is None else of_reference.pairs,
                                    run_dir / "plots" / "depth_consistency.png", agree_cm=100 * of_estimate.agree_m)
    return {"depth_consistency": _relative(path, run_dir)}


# ---------------------------------------------------------------------------------------------------------------
# Evaluation


@dataclass(frozen=True)
class EvaluationOptions:
    align: str = "none"  # "none" or "icp": align the reconstruction to the ground-truth mesh before culling
    n_points: int = 450_000  # surface samples per mesh
    depth_views: int = 1000  # random views for depth L1 (0 = skip)
    plots: bool = True
    max_cameras: int = 300  # culling cameras: every frame, or a stride keeping at most this many
    seed: int = 0
    consistency_frames: int = CONSISTENCY_FRAMES  # 0 = no depth consistency score


def evaluate_run(
    run_dir: PathLike,
    gt_mesh: Optional[PathLike] = None,
    data: Optional[PathLike] = None,
    align: str = "none",
    n_points: int = 450_000,
    depth_views: int = 1000,
    plots: bool = True,
    max_cameras: int = 300,
    seed: int = 0,
    consistency_frames: int = CONSISTENCY_FRAMES,
) -> dict:
    """All metrics of one run as a JSON-ready dict (distances in cm, ratios in %); plots go to RUN_DIR/plots/.

    `gt_mesh` defaults to `<scene>_mesh.ply` next to the data set (NICE-SLAM layout); `data` overrides the data
    set path recorded in summary.json; `align="icp"` aligns the reconstruction to the ground-truth mesh first.
    `consistency_frames` bounds the frames of the depth consistency score (0 skips it).
    """
    if align not in ALIGN_CHOICES:
        raise RunDirectoryError(f"align must be one of {ALIGN_CHOICES}, got {align!r}")
    options = EvaluationOptions(align, n_points, depth_views, plots, max_cameras, seed, consistency_frames)
    started = time.perf_counter()
    run = read_run(run_dir)
    summary = run.summary
    data_path = str(data) if data is not None else summary.get("data")
    report: dict[str, Any] = {
        "run_dir": str(run.run_dir.resolve()),
        "evaluated_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "dataset": {
            "path": data_path,
            "kind": summary.get("dataset_kind"),
            "frames": summary.get("frames"),
            "n_frames": summary.get("n_frames"),
        },
        "performance": {
            key: summary.get(key)
            for key in ("seconds_per_frame", "frames_per_second", "peak_memory_mb", "parameter_count")
        },
        "trajectory": None,
        "consistency": None,
        "reconstruction": None,
        "depth_l1": None,
        "plots": {},
        "skipped": [],
        "seconds": {},
        "config_file": summary.get("config_file"),
        "config": _read_config(run.config),
    }
    estimate = read_tum(run.trajectory)

    clock = time.perf_counter()
    if run.groundtruth is None:
        report["skipped"].append("trajectory metrics: no groundtruth.txt in the run (the data set has no poses)")
    else:
        report["trajectory"], ate_result = _trajectory_section(estimate, read_tum(run.groundtruth))
        sigma = None
        if run.pose_quality is not None:
            report["trajectory"]["covariance"], sigma = _covariance_section(read_pose_quality(run.pose_quality),
                                                                            ate_result)
        if options.plots:
            report["plots"].update(_trajectory_plots(ate_result, run.run_dir, sigma))
    report["seconds"]["trajectory"] = time.perf_counter() - clock

    clock = time.perf_counter()
    if options.consistency_frames <= 0:
        report["skipped"].append("depth consistency: disabled (--consistency-frames 0)")
    elif data_set_path(summary, data_path) is None:
        report["skipped"].append(f"depth consistency: data set not found at {data_path or '(no data path)'} "
                                 "(pass --data)")
    else:
        dataset = open_run_dataset(summary, data_path, report["config"], "the depth consistency score")
        report["consistency"], of_estimate, of_reference = _consistency_section(
            dataset, estimate, options.consistency_frames)
        if of_estimate is None:
            report["skipped"].append(
                f"depth consistency: no two frames {NEAR_FRAMES} or more apart see the same surface under the "
                "estimated poses (too few frames)")
        elif options.plots:
            report["plots"].update(_consistency_plot(of_estimate, of_reference, run.run_dir))
    report["seconds"]["consistency"] = time.perf_counter() - clock

    gt_mesh_path = Path(gt_mesh) if gt_mesh is not None else None
    if gt_mesh_path is None and data_path:
        gt_mesh_path = find_gt_mesh(Path(data_path))
        if gt_mesh_path is not None:
            log.info("using the ground-truth mesh found next to the data set: %s", gt_mesh_path)
    if run.mesh is None:
        report["skipped"].append("reconstruction metrics: no mesh.ply in the run (mesh extraction was skipped)")
    elif gt_mesh_path is None:
        report["skipped"].append("reconstruction metrics: no ground-truth mesh (pass --gt-mesh PLY)")
    else:
        _evaluate_meshes(report, run, estimate, gt_mesh_path, data_path, options)
    report["seconds"]["total"] = time.perf_counter() - started
    return _json_ready(report)


def _trajectory_plots(result, run_dir: Path, sigma: Optional[np.ndarray] = None) -> dict[str, str]:
    from eslam_core.evaluation import plots as figures  # matplotlib is imported only when plots are wanted

    title = f"ATE RMSE {100 * result.rmse:.2f} cm"
    trajectory = figures.plot_trajectory(result.gt_positions, result.aligned_positions,
                                         run_dir / "plots" / "trajectory.png", title=title)
    error = figures.plot_position_error(result.timestamps, result.errors, run_dir / "plots" / "position_error.png",
                                        sigma)
    return {"trajectory": _relative(trajectory, run_dir), "position_error": _relative(error, run_dir)}


def _evaluate_meshes(report: dict, run: RunFiles, estimate: Trajectory, gt_mesh_path: Path,
                     data_path: Optional[str], options: EvaluationOptions) -> None:
    """Fill the reconstruction and depth L1 sections: align (optionally), cull both meshes, measure."""
    truncation = run.summary.get("truncation")
    if truncation is None:
        raise RunDirectoryError(f"{run.run_dir / 'summary.json'} has no 'truncation' (metres): needed for culling")
    rec = load_mesh(run.mesh, "reconstructed mesh")
    gt = load_mesh(gt_mesh_path, "ground-truth mesh")
    icp_transform = None
    if options.align == "icp":
        clock = time.perf_counter()
        icp_transform = icp_align(rec, gt, seed=options.seed)
        rec = rec.copy()
        rec.apply_transform(icp_transform)
        report["seconds"]["icp"] = time.perf_counter() - clock

    clock = time.perf_counter()
    cameras = observing_cameras(run.summary, data_path, estimate, options.max_cameras, report["config"])
    (rec_culled, gt_culled), n_cameras = cull_to_observed([rec, gt], cameras, float(truncation))
    report["seconds"]["culling"] = time.perf_counter() - clock
    # Culled meshes always have borders: only emptiness (nothing observed) is worth an error here.
    check_mesh(rec_culled, "reconstructed mesh after culling", warn=False)
    check_mesh(gt_culled, "ground-truth mesh after culling", warn=False)

    clock = time.perf_counter()
    metrics = reconstruction_metrics(rec_culled, gt_culled, n_points=options.n_points, seed=options.seed)
    report["seconds"]["reconstruction"] = time.perf_counter() - clock
    report["reconstruction"] = {
        "gt_mesh": str(gt_mesh_path),
        "align": options.align,
        "icp_transform": icp_transform.tolist() if icp_transform is not None else None,
        "culling": {
            "cameras": n_cameras,
            "truncation_m": float(truncation),
            "rec_faces": [len(rec.faces), len(rec_culled.faces)],
            "gt_faces": [len(gt.faces), len(gt_culled.faces)],
        },
        "n_points": metrics.n_points,
        "accuracy_cm": 100 * metrics.accuracy,
        "completion_cm": 100 * metrics.completion,
        "completion_ratio_percent": 100 * metrics.completion_ratio,
        "completion_threshold_cm": 100 * metrics.completion_threshold,
        "thresholds": [
            {
                "threshold_cm": 100 * score.threshold,
                "precision_percent": 100 * score.precision,
                "recall_percent": 100 * score.recall,
                "fscore_percent": 100 * score.fscore,
            }
            for score in metrics.scores
        ],
    }

    if options.depth_views <= 0:
        report["skipped"].append("depth L1: disabled (--depth-views 0)")
        return
    depth = depth_l1(rec_culled, gt_culled, n_views=options.depth_views, seed=options.seed)
    report["seconds"]["depth_l1"] = depth.seconds
    report["depth_l1"] = {
        "depth_l1_cm": 100 * depth.mean,
        "views": depth.n_views,
        "skipped_views": depth.n_skipped,
        "missing_percent": 100 * depth.missing_fraction,
        "resolution": [depth.intrinsics.width, depth.intrinsics.height],
        "seconds": depth.seconds,
    }
    if options.plots and depth.examples:
        from eslam_core.evaluation import plots as figures

        path = figures.plot_depth_errors([(v.gt_depth, v.rec_depth) for v in depth.examples],
                                         run.run_dir / "plots" / "depth_errors.png")
        report["plots"]["depth_errors"] = _relative(path, run.run_dir)


def _relative(path: Path, root: Path) -> str:
    return str(Path(path).relative_to(root))


def _json_ready(value: Any) -> Any:
    """Plain JSON types; nan/inf become null (JSON has no NaN)."""
    if isinstance(value, dict):
        return {str(k): _json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value]
    if isinstance(value, np.ndarray):
        return _json_ready(value.tolist())
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, Path):
        return str(value)
    return value


# ---------------------------------------------------------------------------------------------------------------
# Writers


def write_report_json(report: dict, path: PathLike) -> Path:
    path = Path(path)
    path.write_text(json.dumps(_json_ready(report), indent=2) + "\n")
    return path


def _number(value: Optional[float], digits: int = 2, unit: str = "") -> str:
    if value is None:
        return "–"
    text = f"{value:.{digits}f}" if isinstance(value, float) else f"{value}"
    return f"{text} {unit}".strip()


def _table(rows: Sequence[Sequence[str]], header: Sequence[str]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return lines


def render_markdown(report: dict) -> str:
    """The report as Markdown for a person: what was measured, on what, how fast, and the plots."""
    data = report.get("dataset") or {}
    frames = data.get("frames")
    frames_text = f"frames {frames[0]}:{frames[1] if frames[1] is not None else 'end'}:{frames[2]}" if frames else ""
    lines = [
        f"# ESLAM evaluation: {Path(report['run_dir']).name}",
        "",
        f"- Run: `{report['run_dir']}` (evaluated {report.get('evaluated_at', '?')})",
        f"- Data set: {data.get('kind') or '?'} `{data.get('path') or '?'}` {frames_text}, "
        f"{data.get('n_frames') if data.get('n_frames') is not None else '?'} frames",
        "",
    ]

    trajectory = report.get("trajectory")
    lines += ["## Camera tracking", ""]
    if trajectory:
        rows = [
            ["ATE RMSE", _number(trajectory["ate_rmse_cm"], unit="cm")],
            ["ATE mean", _number(trajectory["ate_mean_cm"], unit="cm")],
            ["ATE median", _number(trajectory["ate_median_cm"], unit="cm")],
            ["ATE max", _number(trajectory["ate_max_cm"], unit="cm")],
            ["matched poses", f"{trajectory['matched_poses']} of {trajectory['estimated_poses']}"],
            ["ground-truth path length", _number(trajectory["gt_path_length_m"], unit="m")],
        ]
        for key, label in (("rpe_per_frame", "per frame"), ("rpe_per_metre", "per metre")):
            rpe_values = trajectory.get(key)
            if rpe_values:
                rows.append([f"RPE {label}: translation RMSE", _number(rpe_values["trans_rmse_cm"], 3, "cm")])
                rows.append([f"RPE {label}: rotation RMSE", _number(rpe_values["rot_rmse_deg"], 3, "deg")])
        covariance = trajectory.get("covariance")
        if covariance:
            rows.append(["frames degraded / lost", f"{covariance['frames_degraded']} / {covariance['frames_lost']}"])
            rows.append(["predicted position sigma, median", _number(covariance["sigma_median_cm"], unit="cm")])
            rows.append(["error / predicted sigma, median", _number(covariance["error_over_sigma_median"])])
            rows.append(["errors within 2 sigma", _number(covariance["within_2_sigma_percent"], 1, "%")])
        lines += _table(rows, ["metric", "value"])
        lines += ["", f"Alignment: {trajectory['alignment']}.", ""]
    else:
        lines += ["Not evaluated (see Skipped).", ""]

    lines += _consistency_markdown(report.get("consistency"))

    recon = report.get("reconstruction")
    lines += ["## Reconstruction", ""]
    if recon:
        culling = recon["culling"]
        rows = [
            ["Accuracy (rec → gt)", _number(recon["accuracy_cm"], unit="cm")],
            ["Completion (gt → rec)", _number(recon["completion_cm"], unit="cm")],
            [f"Completion ratio (< {recon['completion_threshold_cm']:g} cm)",
             _number(recon["completion_ratio_percent"], unit="%")],
        ]
        for score in recon["thresholds"]:
            rows.append([f"Precision / recall / F-score @ {score['threshold_cm']:g} cm",
                         " / ".join(_number(score[k], 1) for k in ("precision_percent", "recall_percent",
                                                                     "fscore_percent")) + " %"])
        depth = report.get("depth_l1")
        if depth:
            rows.append(["Depth L1", _number(depth["depth_l1_cm"], unit="cm")])
        lines += _table(rows, ["metric", "value"])
        lines += [
            "",
            f"Ground-truth mesh `{recon['gt_mesh']}`, alignment: {recon['align']}. Both meshes culled to what "
            f"{culling['cameras']} cameras observed (truncation {culling['truncation_m']:g} m): reconstruction "
            f"{culling['rec_faces'][0]} → {culling['rec_faces'][1]} faces, ground truth {culling['gt_faces'][0]} → "
            f"{culling['gt_faces'][1]} faces; {recon['n_points']} samples per mesh.",
        ]
        if depth:
            lines.append(
                f"Depth L1 over {depth['views']} random views ({depth['resolution'][0]}x{depth['resolution'][1]}, "
                f"{depth['skipped_views']} rejected for little ground-truth depth); ground-truth surface missing "
                f"from the reconstruction in {depth['missing_percent']:.1f} % of pixels; {depth['seconds']:.1f} s."
            )
        lines.append("")
    else:
        lines += ["Not evaluated (see Skipped).", ""]

    performance = report.get("performance") or {}
    lines += ["## Speed and memory", ""]
    lines += _table(
        [
            ["seconds per frame", _number(performance.get("seconds_per_frame"), 3, "s")],
            ["frames per second", _number(performance.get("frames_per_second"), 2)],
            ["peak memory", _number(performance.get("peak_memory_mb"), 0, "MB")],
            ["parameters", _number(performance.get("parameter_count"))],
        ],
        ["measure", "value"],
    )
    lines.append("")

    if report.get("plots"):
        lines += ["## Plots", ""]
        for name, path in report["plots"].items():
            lines += [f"![{name}]({path})", ""]
    if report.get("skipped"):
        lines += ["## Skipped", ""] + [f"- {reason}" for reason in report["skipped"]] + [""]
    seconds = report.get("seconds") or {}
    if seconds:
        lines += ["Evaluation time: " + ", ".join(f"{k} {v:.1f} s" for k, v in seconds.items() if v is not None), ""]
    lines += ["## Configuration", ""]
    if report.get("config_file"):
        lines += [f"Config file: `{report['config_file']}`", ""]
    if report.get("config") is not None:
        lines += ["```yaml", yaml.safe_dump(report["config"], sort_keys=False).rstrip(), "```", ""]
    else:
        lines += ["No config.yaml in the run directory.", ""]
    return "\n".join(lines)


def _consistency_markdown(consistency: Optional[dict]) -> list[str]:
    lines = ["## Depth consistency (needs no ground truth)", ""]
    if not consistency:
        return lines + ["Not evaluated (see Skipped).", ""]
    scored = [("estimated poses", consistency["estimate"]), ("reference poses", consistency.get("reference"))]
    scored = [(name, values) for name, values in scored if values]
    header = ["", *(name for name, _ in scored)]
    rows = [["median abs. depth residual, all pairs", *(_number(v["median_mm"], 1, "mm") for _, v in scored)],
            [f"pixels agreeing within {consistency['estimate']['agree_within_cm']:g} cm",
             *(_number(v["agree_percent"], 1, "%") for _, v in scored)]]
    for kind in sorted(consistency["estimate"]["by_kind"]):
        of_kind = [v["by_kind"].get(kind) for _, v in scored]
        pairs = of_kind[0]["pairs"]
        rows.append([f"median, {kind} pairs ({pairs})",
                     *(_number(k["median_mm"] if k else None, 1, "mm") for k in of_kind)])
    lines += _table(rows, header)
    step = consistency["frame_step"]
    lines += ["", f"{consistency['frames']} frames ({'all' if step == 1 else f'one in {step}'} of the run's); "
                  f"pairs chosen by "
                  f"{consistency['pairs_chosen_by']}. Each pair's depths are warped into each other both ways; "
                  "points hidden in the other view are not compared.", ""]
    return lines


def write_report_markdown(report: dict, path: PathLike) -> Path:
    path = Path(path)
    path.write_text(render_markdown(report))
    return path


# ---------------------------------------------------------------------------------------------------------------
# Comparing two runs

_COMPARED = (
    ("ATE RMSE [cm]", ("trajectory", "ate_rmse_cm"), 2),
    ("ATE mean [cm]", ("trajectory", "ate_mean_cm"), 2),
    ("RPE/frame translation [cm]", ("trajectory", "rpe_per_frame", "trans_rmse_cm"), 3),
    ("RPE/frame rotation [deg]", ("trajectory", "rpe_per_frame", "rot_rmse_deg"), 3),
    ("RPE/metre translation [cm]", ("trajectory", "rpe_per_metre", "trans_rmse_cm"), 2),
    ("RPE/metre rotation [deg]", ("trajectory", "rpe_per_metre", "rot_rmse_deg"), 2),
    ("Depth consistency, estimate [mm]", ("consistency", "estimate", "median_mm"), 1),
    ("Depth consistency, reference [mm]", ("consistency", "reference", "median_mm"), 1),
    ("Depth agreement, estimate [%]", ("consistency", "estimate", "agree_percent"), 1),
    ("Accuracy [cm]", ("reconstruction", "accuracy_cm"), 2),
    ("Completion [cm]", ("reconstruction", "completion_cm"), 2),
    ("Completion ratio [%]", ("reconstruction", "completion_ratio_percent"), 2),
    ("Depth L1 [cm]", ("depth_l1", "depth_l1_cm"), 2),
    ("Seconds per frame", ("performance", "seconds_per_frame"), 3),
    ("Frames per second", ("performance", "frames_per_second"), 2),
    ("Peak memory [MB]", ("performance", "peak_memory_mb"), 0),
    ("Parameters", ("performance", "parameter_count"), 0),
)


def _lookup(report: dict, keys: Sequence[str]) -> Optional[float]:
    value: Any = report
    for key in keys:
        if not isinstance(value, dict) or value.get(key) is None:
            return None
        value = value[key]
    return value


def _flatten(config: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(config, dict):
        return {prefix: config} if prefix else {}
    flat: dict[str, Any] = {}
    for key, value in config.items():
        flat.update(_flatten(value, f"{prefix}.{key}" if prefix else str(key)))
    return flat


def load_report(run_dir: PathLike) -> dict:
    path = Path(run_dir) / "report.json"
    if not path.is_file():
        raise RunDirectoryError(f"{run_dir} has no report.json: evaluate it first with `eslam eval {run_dir}`")
    return json.loads(path.read_text())


def render_comparison(report_a: dict, report_b: dict, name_a: str = "A", name_b: str = "B") -> str:
    """Markdown table of the two runs' metrics side by side, with B - A, and the configuration values that differ."""
    rows = []
    for label, keys, digits in _COMPARED:
        a, b = _lookup(report_a, keys), _lookup(report_b, keys)
        change = _number(float(b) - float(a), digits) if a is not None and b is not None else "–"
        shown = [_number(None if value is None else float(value), digits) for value in (a, b)]
        rows.append([label, *shown, change])
    lines = [f"# ESLAM runs compared: {name_a} vs {name_b}", "",
             f"- {name_a}: `{report_a.get('run_dir')}`", f"- {name_b}: `{report_b.get('run_dir')}`", ""]
    lines += _table(rows, ["metric", name_a, name_b, f"{name_b} − {name_a}"])
    config_a, config_b = _flatten(report_a.get("config")), _flatten(report_b.get("config"))
    differing = [key for key in sorted(set(config_a) | set(config_b)) if config_a.get(key) != config_b.get(key)]
    lines += ["", "## Configuration differences", ""]
    if differing:
        lines += _table([[f"`{k}`", str(config_a.get(k, "–")), str(config_b.get(k, "–"))] for k in differing],
                        ["setting", name_a, name_b])
    else:
        lines.append("None.")
    return "\n".join(lines) + "\n"


def compare_runs(run_a: PathLike, run_b: PathLike, out_path: Optional[PathLike] = None) -> str:
    """Side-by-side Markdown of two evaluated runs (their report.json); written to `out_path` when given."""
    name_a, name_b = Path(run_a).resolve().name, Path(run_b).resolve().name
    if name_a == name_b:  # e.g. two "out" folders: tell them apart by their parent folder
        name_a, name_b = (f"{Path(r).resolve().parent.name}/{n}" for r, n in ((run_a, name_a), (run_b, name_b)))
    markdown = render_comparison(load_report(run_a), load_report(run_b), name_a, name_b)
    if out_path is not None:
        Path(out_path).write_text(markdown)
    return markdown
