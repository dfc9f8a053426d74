"""Speed benchmark: per-iteration cost of tracking and mapping, split by stage, and whole-run throughput.

    python bench/speed.py --data ../shared/data/icl_office_kt0 [--kind icl] [--frames 40] [--repeats 5]
    python bench/speed.py                      # the synthetic room when no data is given

For each preset (paper-faithful `icl`/`replica` settings and `fast`) it measures, on real frames and a warmed-up
map: the median time of a rendering tracking iteration and a mapping iteration (a window of five keyframes spread
over the sequence) split into plane lookup / decoders / rendering / losses / backward / optimizer step; the same
iterations with the plain-torch plane lookup instead of the fused C kernel (a ratio measured in the same run); for
a preset with the SDF tracker, its cost per frame; the speed-up over the official implementation's figures; plane
memory; and frames per second, ATE and peak memory of whole runs (each in its own process, so peak memory is the
run's own). Prints a table and writes JSON. On a shared or virtual machine, run it more than once: medians of one
run move by 10-20 % between runs.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from eslam_core.config import load_config  # noqa: E402
from eslam_core.cpu import denormals_flushed  # noqa: E402
from eslam_core.datasets import open_dataset  # noqa: E402
from eslam_core.representation.field import FrozenField  # noqa: E402
from eslam_core.frames import pixel_directions_table, prepare_frame, working_intrinsics  # noqa: E402
from eslam_core.geometry import params_to_pose, pose_to_params  # noqa: E402
from eslam_core.mapping.keyframes import Keyframe  # noqa: E402
from eslam_core.rendering.losses import eslam_losses  # noqa: E402
from eslam_core.mapping.mapper import Mapper  # noqa: E402
from eslam_core.mapping.plane_adam import RowSparseAdam  # noqa: E402
from eslam_core.rendering.volume import alpha_from_sdf, render_weights, sample_depths  # noqa: E402
from eslam_core.slam import SLAM  # noqa: E402
from eslam_core.tracking.frontend import make_tracker  # noqa: E402

# The official implementation on this machine kind (2 cores, CPU), from ../shared/reference/eslam_facts.md.
OFFICIAL = {"tracking_iteration_s": (0.27, 0.45), "mapping_iteration_s": (1.6, 2.4)}
STAGES = ("lookup", "decoders", "rendering", "losses", "backward", "step")


class Stopwatch:
    def __init__(self):
        self.times = {s: 0.0 for s in STAGES}
        self.t = time.perf_counter()

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.times[stage] += now - self.t
        self.t = now


def staged_iteration(field, origins, dirs, d_gt, rgb_gt, cfg, weights, optim, plane_adam=None) -> dict:
    """One optimisation iteration, the same computation as rendering.render_rays + losses, timed by stage. With a
    FrozenField (tracking), "lookup" is the lookup on the planes folded with the decoders' first layer. With
    `plane_adam` (mapping with the C kernel, as mapper.py), the planes' rows are stepped by it."""
    sw = Stopwatch()
    z = sample_depths(field, origins.detach(), dirs.detach(), d_gt, cfg.render, cfg.model.truncation)
    pts = (origins[:, None, :] + z[..., None] * dirs[:, None, :]).reshape(-1, 3)
    sw.lap("rendering")
    if isinstance(field, FrozenField):
        fg, fa = field.first_layer("sdf", pts), field.first_layer("color", pts)
        sw.lap("lookup")
        sdf, rgb = field.decode("sdf", fg).reshape(z.shape), field.decode("color", fa).reshape(z.shape + (3,))
    else:
        fg, fa = field.geometry_planes(pts), field.appearance_planes(pts)
        sw.lap("lookup")
        sdf = field.geometry_decoder(fg).reshape(z.shape)
        rgb = field.appearance_decoder(fa).reshape(z.shape + (3,))
    sw.lap("decoders")
    w = render_weights(alpha_from_sdf(sdf, field.beta))
    from eslam_core.rendering.volume import RenderOutput

    out = RenderOutput(z, sdf, w, (w * z).sum(-1), (w[..., None] * rgb).sum(-2))
    sw.lap("rendering")
    loss = eslam_losses(out, d_gt, rgb_gt, cfg.model.truncation).total(weights)
    sw.lap("losses")
    optim.zero_grad(set_to_none=True)
    loss.backward()
    sw.lap("backward")
    optim.step()
    if plane_adam is not None:
        plane_adam.step()
    sw.lap("step")
    return sw.times


def median_stages(samples: list[dict]) -> dict:
    out = {s: statistics.median(x[s] for x in samples) for s in STAGES}
    out["total"] = statistics.median(sum(x.values()) for x in samples)
    return out


@denormals_flushed()  # as tracking and mapping run
def iteration_benchmark(cfg, ds, repeats: int, native: bool, grow: float = 0.0) -> dict:
    """Median tracking and mapping iteration times on a map warmed up on the first frames (its extent then grown
    by `grow` metres on every side: a larger map, the same rays)."""
    torch.manual_seed(0)
    slam = SLAM(cfg, ds.intrinsics)
    cfg.mapping.first_iterations, keep = 30, cfg.mapping.first_iterations
    slam.step(ds[0])
    cfg.mapping.first_iterations = keep
    if grow > 0:
        slam.map.grow(slam.map.extent + np.array([[-grow] * 3, [grow] * 3]))
    field = slam.map.field
    for planes in (field.geometry_planes, field.appearance_planes):
        planes.use_native = native
    intr = working_intrinsics(ds.intrinsics, cfg.camera)
    dirs_cam = pixel_directions_table(intr)
    frame = prepare_frame(ds[min(4, len(ds) - 1)], ds.intrinsics, cfg.camera)
    pose = torch.from_numpy(slam.trajectory.pose(0)).float()

    # Tracking: pose parameters only, against the tracker's snapshot of the map. Folding the decoders' first layer
    # into the planes happens once per frame: its cost, spread over the frame's iterations, counts as lookup.
    depth = frame.depth.reshape(-1)
    valid = torch.nonzero(depth > 0).squeeze(1)
    t, q = (p.requires_grad_(True) for p in pose_to_params(pose))
    optim = torch.optim.Adam([t, q], lr=1e-3, betas=(0.5, 0.999))
    t0 = time.perf_counter()
    fixed = FrozenField(field)
    fixed.first_layer("sdf", pose[None, :3, 3]), fixed.first_layer("color", pose[None, :3, 3])
    fold_s = time.perf_counter() - t0
    track = []
    for _ in range(repeats + 1):
        pix = valid[torch.randint(len(valid), (cfg.tracking.rays,))]
        c2w = params_to_pose(t, q)
        dirs = dirs_cam[pix] @ c2w[:3, :3].T
        track.append(staged_iteration(fixed, c2w[:3, 3].expand(len(pix), 3), dirs, depth[pix],
                                      frame.rgb.reshape(-1, 3)[pix], cfg, cfg.render_tracker.weights, optim))
        track[-1]["lookup"] += fold_s / max(cfg.tracking.iterations, 1)

    # The fast preset's tracker: a whole frame's Gauss-Newton alignment (all its iterations), against the newest
    # keyframe's images.
    track_frame = []
    if cfg.tracking.method == "sdf":
        tracker = make_tracker(cfg, dirs_cam, intr)
        for _ in range(repeats + 1):
            t0 = time.perf_counter()
            tracker.track(field, frame, pose, observed=slam.map.observed, keyframe=slam.map.newest_keyframe(),
                          map_version=slam.map.version)  # folded once: the map changes once per mapping step
            track_frame.append(time.perf_counter() - t0)

    # Mapping: planes, decoders and poses of a window of keyframes spread over the sequence (rays from different
    # parts of the scene touch different plane cells, as in a real window: cache behaviour matters).
    kfs = []
    for i in np.linspace(0, len(ds) - 1, 5).astype(int):
        f = prepare_frame(ds[int(i)], ds.intrinsics, cfg.camera)
        kf_pose = torch.from_numpy(f.gt_pose).float() if f.gt_pose is not None else pose
        kfs.append(Keyframe.from_tensors(int(i), 0.0, f.rgb, f.depth, f.depth >= 0, kf_pose))
    mapper = Mapper.of(cfg, dirs_cam, intr.height, intr.width)
    # Window poses are optimised too when the preset does (the oldest one anchors the gauge), as in mapping.py.
    pose_params = [[p.requires_grad_(True) for p in pose_to_params(kf.pose)] for kf in kfs[1:]] \
        if cfg.mapping.joint_poses else []
    planes = [field.geometry_planes, field.appearance_planes]
    sparse = native and all(p.kernel() is not None for p in planes)  # as mapper.py: row-sparse Adam on the planes
    groups = [{"params": field.decoder_parameters(), "lr": 1e-3}]
    if not sparse:
        groups.append({"params": field.plane_parameters(), "lr": 5e-3})
    if pose_params:
        groups.append({"params": [p for tq in pose_params for p in tq], "lr": 1e-3})
    optim = torch.optim.Adam(groups, fused=True)
    plane_adam = RowSparseAdam()
    mapping = []
    per = cfg.mapping.rays // len(kfs)
    with plane_adam.fresh(planes if sparse else [], lr=5e-3):
        for _ in range(repeats + 1):
            o, d, dg, cg = [], [], [], []
            for k, kf in enumerate(kfs):
                pix = mapper._pixels(kf, per)
                c2w = params_to_pose(*pose_params[k - 1]) if pose_params and k > 0 else kf.pose
                d.append(dirs_cam[pix] @ c2w[:3, :3].T)
                o.append(c2w[:3, 3].expand(len(pix), 3))
                dg.append(kf.depths(pix))
                cg.append(kf.colors(pix))
            mapping.append(staged_iteration(field, torch.cat(o), torch.cat(d), torch.cat(dg), torch.cat(cg), cfg,
                                             cfg.mapping.weights, optim, plane_adam if sparse else None))
    params = field.parameter_count()
    return {"tracking": median_stages(track[1:]), "mapping": median_stages(mapping[1:]),
            "tracking_frame_s": statistics.median(track_frame[1:]) if track_frame else None, "fold_s": fold_s,
            "parameters": params, "plane_memory_mb": sum(p.numel() for p in field.plane_parameters()) * 4 / 2**20,
            "optimizer_state_mb": 2 * params * 4 / 2**20}


def whole_run(preset: str, data: Path, kind: str, frames: int, extra: list[str]) -> dict:
    """`eslam run` in its own process: frames per second, ATE and the process's own peak memory."""
    with tempfile.TemporaryDirectory() as out:
        cmd = [sys.executable, "-m", "eslam_core", "run", "--config", preset, "--data", str(data), "--out", out,
               "--frames", f"0:{frames}", "--no-mesh", "-q", "--set", f"dataset.kind={kind}", *extra]
        t0 = time.perf_counter()
        res = subprocess.run(cmd, capture_output=True, text=True,
                             env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parent.parent)))
        wall = time.perf_counter() - t0
        if res.returncode != 0:
            return {"error": res.stderr[-2000:]}
        s = json.loads((Path(out) / "summary.json").read_text())
    return {"frames": s["frames_this_run"], "seconds_per_frame": s["seconds_per_frame"],
            "frames_per_second": s["frames_per_second"], "ate_rmse_cm": s["ate_rmse_cm"],
            "peak_memory_mb": s["peak_memory_mb"], "wall_s": wall, "workers": extra}


def fmt_ms(x: float) -> str:
    return f"{1000 * x:8.1f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, help="data set folder (default: the synthetic room, generated)")
    ap.add_argument("--kind", default=None, help="data set kind (default: icl for icl_* folders, else auto)")
    ap.add_argument("--presets", default="icl,fast", help="comma-separated presets to measure")
    ap.add_argument("--repeats", type=int, default=5, help="iterations per median")
    ap.add_argument("--frames", type=int, default=40, help="frames per whole run (0 = skip whole runs)")
    ap.add_argument("--grow", type=float, default=0.0, metavar="METRES",
                    help="iterations on the map grown by this much on every side (same rays, more plane rows)")
    ap.add_argument("--workers", default="1", help="comma-separated worker counts for whole runs, e.g. 1,2")
    ap.add_argument("--out", type=Path, default=Path("bench_speed.json"))
    args = ap.parse_args()

    if args.data is None:
        from eslam_core.datasets.synthetic import ensure_scene

        args.data = ensure_scene(Path.home() / ".cache" / "eslam" / "scenes", n_frames=60, width=640, height=480)
        kind = "tum"
    else:
        kind = args.kind or ("icl" if "icl" in args.data.name else "auto")
    results = {"data": str(args.data), "threads": torch.get_num_threads(), "official_reference": OFFICIAL,
               "load_average_start": os.getloadavg(), "presets": {}}
    for preset in args.presets.split(","):
        cfg = load_config(preset, {"dataset": {"kind": kind}})
        ds = open_dataset(args.data, cfg.dataset.kind, depth_scale=cfg.camera.depth_scale)
        r = {"native": iteration_benchmark(load_config(preset, {"dataset": {"kind": kind}}), ds, args.repeats, True,
                                           args.grow),
             "torch": iteration_benchmark(load_config(preset, {"dataset": {"kind": kind}}), ds, args.repeats, False,
                                          args.grow)}
        r["runs"] = [whole_run(preset, args.data, kind, args.frames, ["--workers", w] if w != "1" else [])
                     for w in args.workers.split(",")] if args.frames else []
        results["presets"][preset] = r
    results["load_average_end"] = os.getloadavg()
    args.out.write_text(json.dumps(results, indent=2))

    print(f"data: {args.data}   torch threads: {results['threads']}   load avg: {results['load_average_start']}")
    print(f"official implementation (reference, this machine kind): tracking iteration "
          f"{OFFICIAL['tracking_iteration_s']} s, mapping iteration {OFFICIAL['mapping_iteration_s']} s")
    for preset, r in results["presets"].items():
        print(f"\n== {preset}: {r['native']['parameters'] / 1e6:.2f} M parameters, planes "
              f"{r['native']['plane_memory_mb']:.1f} MB (+ Adam state {r['native']['optimizer_state_mb']:.1f} MB)")
        print(f"{'ms per iteration':22s}" + "".join(f"{s:>9s}" for s in STAGES) + f"{'total':>9s}{'vs torch':>9s}")
        for phase in ("tracking", "mapping"):
            n, t = r["native"][phase], r["torch"][phase]
            print(f"{phase + ' (fused)':22s}" + "".join(fmt_ms(n[s]) + " " for s in STAGES)
                  + fmt_ms(n["total"]) + f"{t['total'] / n['total']:8.1f}x")
            print(f"{phase + ' (torch)':22s}" + "".join(fmt_ms(t[s]) + " " for s in STAGES) + fmt_ms(t["total"]))
        cfg = load_config(preset, {"dataset": {"kind": kind}})
        if r["native"]["tracking_frame_s"] is not None:
            print(f"tracking per frame ({cfg.tracking.method} tracker, {cfg.tracking.iterations} iterations x "
                  f"{cfg.tracking.rays} points): {1000 * r['native']['tracking_frame_s']:.1f} ms")
        else:
            lo, hi = OFFICIAL["tracking_iteration_s"]
            mlo, mhi = OFFICIAL["mapping_iteration_s"]
            n = r["native"]
            print(f"faster than the official implementation: tracking iteration {lo / n['tracking']['total']:.1f}-"
                  f"{hi / n['tracking']['total']:.1f}x, mapping iteration {mlo / n['mapping']['total']:.1f}-"
                  f"{mhi / n['mapping']['total']:.1f}x")
        for run in r["runs"]:
            if "error" in run:
                print(f"whole run failed: {run['error']}")
                continue
            print(f"whole run {run['workers'] or ['--workers', '1']}: {run['frames']} frames, "
                  f"{run['frames_per_second']:.2f} frames/s ({run['seconds_per_frame']:.2f} s/frame), "
                  f"ATE {run['ate_rmse_cm']} cm, peak memory {run['peak_memory_mb']:.0f} MB")
    print(f"\nJSON -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
