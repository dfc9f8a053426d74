"""Offline runs: a data set through the SLAM system, with progress, outputs and a summary.

`workers=1` (default) steps the lock-step `SLAM` here. `workers=2` (or the live policy) feeds the frames through a
runtime (eslam_core.runtime: tracking and mapping processes) and writes the same outputs; there Ctrl-C / SIGTERM
stop the run cleanly: the trajectory so far and a checkpoint are written (no mesh) and the run returns normally.
"""
from __future__ import annotations

import contextlib
import json
import logging
import signal
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from tqdm import tqdm

from eslam_core.config import Config, save_config
from eslam_core.datasets import RGBDDataset
from eslam_core.datasets.read_ahead import ReadAhead
from eslam_core.evaluation.trajectory_error import ate
from eslam_core.outputs.export import estimated_trajectory, ground_truth_trajectory, load_checkpoint, map_mesh, save_checkpoint, \
    tracking_summary, write_trajectories
from eslam_core.atomic import OutputsNotWritten, OutputWriteError, make_output_folder, write_atomic
from eslam_core.outputs.mesh import EmptyMeshError, save_ply
from eslam_core.runtime import make_runtime
from eslam_core.runtime.api import peak_rss_mb
from eslam_core.slam import SLAM, loaded_trajectory
from eslam_core.trajectory import TrackedTrajectory

log = logging.getLogger("eslam")


@dataclass
class RunSummary:
    out_dir: Path
    n_frames: int
    seconds_per_frame: float
    ate_rmse_cm: Optional[float]
    peak_memory_mb: float
    mesh_path: Optional[Path]
    stopped_by: Optional[str] = None  # the signal that ended the run early (runtime runs), None if it finished




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
                 write_mesh: bool = True, workers: int = 1, policy: str = "offline",
                 runtime_options: Optional[dict] = None, localize: bool = False) -> RunSummary:
    """Process `dataset` (already subset to the frames to run) and write every output into `out_dir`.

    workers / policy / runtime_options: see eslam_core.runtime.make_runtime (1 + "offline" = the lock-step schedule
    in this process)."""
    out_dir = make_output_folder(out_dir)
    save_config(cfg, out_dir / "config.yaml")  # a folder that takes no file fails here, before the run
    torch.manual_seed(cfg.run.seed)
    apply_threads(cfg)
    if workers != 1 or policy != "offline":
        return run_with_runtime(cfg, dataset, out_dir, data_label=data_label, frames=frames, resume=resume,
                                progress=progress, write_mesh=write_mesh, workers=workers, policy=policy,
                                options=runtime_options or {})

    if localize:  # every frame, against the saved map (which starts lost: the camera has to be found)
        slam = load_checkpoint(resume, mode="localization")
        slam.tracking.trajectory = TrackedTrajectory()  # this run's frames
        todo = list(range(len(dataset)))
        log.info("localizing against %s: %d keyframes, map left as it is", resume, len(slam.map.keyframes))
    elif resume is not None:
        slam = load_checkpoint(resume)
        done = {r.timestamp for r in slam.trajectory.records}
        todo = [i for i, t in enumerate(dataset.timestamps()) if t not in done]
        log.info("resuming from %s: %d frames done, %d to go", resume, len(slam.trajectory), len(todo))
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
    return write_outputs(cfg, slam, dataset, out_dir, data_label=data_label, frames=frames, n=len(todo),
                         seconds=seconds, write_mesh=write_mesh)


def write_outputs(cfg: Config, slam: SLAM, dataset: RGBDDataset, out_dir: Path, *, data_label: str, frames: tuple,
                  n: int, seconds: float, write_mesh: bool, peak_mb: Optional[float] = None,
                  extra: Optional[dict] = None, stopped_by: Optional[str] = None) -> RunSummary:
    """Trajectories, checkpoint, mesh and summary.json of a run that processed `n` frames in `seconds`.

    A file that cannot be written (e.g. a full disk) does not stop the others: they are all tried, the trajectories
    (small, the most valuable) first and summary.json (which lists what was not written) last, then the failures
    are raised (one OutputWriteError line each)."""
    failed: list[OutputWriteError] = []
    written: list[Path] = []

    def attempt(save, *args) -> Optional[Path]:
        try:
            path = save(*args)
        except OutputWriteError as e:
            failed.append(e)
            return None
        written.append(path)
        return path

    attempt(write_trajectories, slam, out_dir)
    attempt(save_checkpoint, slam, out_dir / "checkpoint.pt")
    mesh_path = None
    if write_mesh and cfg.mesh.enabled:
        try:
            mesh_path = attempt(save_ply, map_mesh(slam, cfg.mesh.resolution), out_dir / "mesh.ply")
        except EmptyMeshError as e:
            log.error("no mesh written: %s", e)

    rmse = ate_cm(slam)
    outside = sum(s.points_outside for s in slam.atlas.submaps)
    summary = {
        "data": data_label or str(dataset.root),
        "dataset_kind": dataset.kind,
        "frames": list(frames),
        "n_frames": len(slam.trajectory),
        "frames_this_run": n,
        "seconds": seconds,
        "seconds_per_frame": seconds / max(n, 1),
        "frames_per_second": n / seconds if seconds > 0 else None,
        "peak_memory_mb": peak_rss_mb() if peak_mb is None else peak_mb,
        "parameter_count": sum(s.field.parameter_count() for s in slam.atlas.submaps if s.field is not None),
        "keyframes": slam.trajectory.keyframes,
        **slam.atlas.memory(),  # (summed over the submaps; their count and the loops closed)
        "loop_closures": [asdict(c) for c in slam.atlas.closures],
        "keyframe_memory_mb": sum(s.keyframes.nbytes() for s in slam.atlas.submaps) / 2**20,
        "truncation": cfg.model.truncation,
        "bound": None if slam.map.extent is None else np.round(slam.map.extent, 4).tolist(),  # (the active submap's)
        "points_outside_bound": outside,
        "points_outside_fraction": outside / max(sum(s.points_seen for s in slam.atlas.submaps), 1),
        "ate_rmse_cm": rmse,
        **tracking_summary(slam.trajectory),
        "config_file": str(out_dir / "config.yaml"),
        "mesh": str(mesh_path) if mesh_path else None,
        "torch_threads": torch.get_num_threads(),
        **(extra or {}),
    }
    if failed:
        summary["not_written"] = [str(e.path) for e in failed]
    attempt(write_atomic, out_dir / "summary.json", json.dumps(summary, indent=2))
    if failed:
        log.info("written: %s", ", ".join(p.name for p in written) or "nothing")
        raise failed[0] if len(failed) == 1 else OutputsNotWritten(failed, written)
    return RunSummary(out_dir, n, summary["seconds_per_frame"], rmse, summary["peak_memory_mb"], mesh_path,
                      stopped_by)


class StopRequest:
    """While active (in the main thread), SIGINT and SIGTERM ask the run to stop cleanly instead of killing it;
    a second signal stops it at once (KeyboardInterrupt)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.requested: Optional[str] = None
        self._previous: dict = {}

    def __enter__(self) -> "StopRequest":
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in self.SIGNALS}
        return self

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = signal.Signals(signum).name
        log.warning("%s: stopping; the trajectory so far and a checkpoint will be written (send it again to abort)",
                    self.requested)

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)


def run_with_runtime(cfg: Config, dataset: RGBDDataset, out_dir: Path, *, data_label: str, frames: tuple,
                     resume: Optional[Path], progress: bool, write_mesh: bool, workers: int,
                     policy: str, options: dict) -> RunSummary:
    """`run_sequence` through a runtime: frames are submitted as fast as they load (offline policy) or at the data
    set's frame rate (live policy), the progress bar follows the polled poses. `resume`: the runtime starts in the
    checkpoint's map and trajectory, and only the frames it has not seen are run (as in the lock-step schedule)."""
    todo = list(range(len(dataset)))
    if resume is not None:
        done = set(loaded_trajectory(resume, cfg, dataset.intrinsics).timestamps().tolist())
        todo = [i for i, t in enumerate(dataset.timestamps()) if t not in done]
        log.info("resuming from %s: %d frames done, %d to go", resume, len(done), len(todo))
    rt = make_runtime(cfg, dataset.intrinsics, workers=workers, policy=policy,
                      checkpoint=None if resume is None else str(resume), **options)
    read_ahead = policy == "offline" and cfg.runtime.read_ahead > 0  # a live policy reads at the camera's rate
    bar = tqdm(total=len(todo), desc="eslam", unit="frame", disable=not progress, dynamic_ncols=True)

    def show(updates: list) -> None:
        if updates:
            bar.update(len(updates))
            h = rt.health()
            bar.set_postfix(frame=updates[-1].index, fps=f"{h.tracking_hz:.2f}", dropped=h.frames_dropped,
                            loss=f"{updates[-1].tracking_loss:.4f}")

    reader = ReadAhead(dataset, cfg.runtime.read_ahead) if read_ahead else contextlib.nullcontext(dataset)
    with StopRequest() as stop, reader as source:
        rt.start()
        start = time.perf_counter()
        try:
            wall0 = data0 = None
            for i in todo:
                if stop.requested:
                    break
                frame = source[i]
                if policy == "live":  # as a camera would deliver them
                    if wall0 is None:
                        wall0, data0 = time.monotonic(), frame.timestamp
                    time.sleep(max(0.0, (frame.timestamp - data0) - (time.monotonic() - wall0)))
                rt.submit(frame)
                show(rt.poll())
            while not stop.requested:  # let the workers finish here, where a signal can still stop them
                h = rt.health()
                if h.frames_tracked + h.frames_dropped >= h.frames_received and h.keyframe_queue_depth == 0:
                    break
                show(rt.poll())
                time.sleep(0.05)
            rt.close(drain=not stop.requested)
            show(rt.poll())
        except BaseException:
            bar.close()
            try:
                rt.close(drain=False)
            except Exception:  # noqa: BLE001 - the first error is the one to report
                pass
            raise
        seconds = time.perf_counter() - start
    bar.close()
    slam = rt.snapshot()
    health = rt.health()
    figures = rt.worker_figures() if hasattr(rt, "worker_figures") else {}
    peak = peak_rss_mb() + figures.get("tracker_peak_mb", 0.0) + figures.get("mapper_peak_mb", 0.0)
    extra = {"runtime": {"workers": workers, "policy": policy, "stopped_by": stop.requested,
                         "frames_read_ahead": reader.read_ahead if read_ahead else 0,
                         "health": health.as_dict(), "workers_figures": figures,
                         "peak_memory_note": "sum of the peaks of the parent and worker processes"}}
    return write_outputs(cfg, slam, dataset, out_dir, data_label=data_label, frames=frames,
                         n=health.frames_tracked, seconds=seconds, write_mesh=write_mesh and not stop.requested,
                         peak_mb=peak, extra=extra, stopped_by=stop.requested)
