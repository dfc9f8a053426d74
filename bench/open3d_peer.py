"""The classical peer: stock Open3D dense SLAM (frame-to-model point-to-plane ICP + TSDF) on the same frames.

    python bench/open3d_peer.py --data ../shared/data/7scenes_redkitchen_0_399 --out runs/open3d [--frames 0:400]

Run it with this project's Python (it reads the data set with eslam_core's readers and evaluates with `eslam eval`);
the SLAM loop itself runs in a separate Python that has Open3D (`--open3d-python`, default /work/o3d-venv/bin/python:
`python3 -m venv /work/o3d-venv && /work/o3d-venv/bin/pip install open3d`; Debian needs libusb-1.0-0 for it to
import). Three steps:
1. here: the frames (image paths, intrinsics, depth scale, timestamps, the first frame's reference pose) are written
   to OUT/frames.json;
2. Open3D's Python runs this file's `slam` step: `o3d.t.pipelines.slam` as in Open3D's own dense SLAM example
   (voxel 5.9 mm = 3/512 m, 16^3 voxel blocks, depth_max 3 m, depth_min 0.1 m, odometry distance 7 cm, truncation
   8 voxels), starting at the first frame's reference pose (the identity where it has none); depth 65535
   (7-Scenes' "no measurement") is set to 0;
   it writes OUT/poses.npy and OUT/open3d.json (seconds per frame);
3. here: OUT becomes a run directory like `eslam run --out` writes (trajectory.txt, groundtruth.txt, summary.json),
   evaluated by `eslam eval` (ATE, RPE, depth consistency of its poses and of the reference poses).
Prints ATE RMSE, RPE per metre, the consistency scores and seconds per frame; the full report is OUT/report.md.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve()
OPEN3D_PYTHON = "/work/o3d-venv/bin/python"
# Open3D's dense SLAM example defaults (examples/python/t_reconstruction_system/default_config.yml), voxel as asked
VOXEL_SIZE = 3.0 / 512  # 5.86 mm
BLOCK_RESOLUTION = 16
BLOCK_COUNT = 40000
DEPTH_MIN, DEPTH_MAX = 0.1, 3.0
ODOMETRY_DISTANCE = 0.07
TRUNCATION_VOXELS = 8.0


# --- step 2, in Open3D's Python: the SLAM loop (imports nothing of eslam_core) --------------------------------------


def open3d_slam(out: Path, device_name: str = "CPU:0") -> None:
    import numpy as np
    import open3d as o3d
    import open3d.core as o3c

    spec = json.loads((out / "frames.json").read_text())
    device = o3c.Device(device_name)
    k = spec["intrinsics"]
    intrinsic = o3c.Tensor([[k["fx"], 0.0, k["cx"]], [0.0, k["fy"], k["cy"]], [0.0, 0.0, 1.0]], o3c.Dtype.Float64)
    pose = o3c.Tensor(np.asarray(spec["first_pose"], dtype=np.float64))
    model = o3d.t.pipelines.slam.Model(VOXEL_SIZE, BLOCK_RESOLUTION, BLOCK_COUNT, pose, device)
    height, width = k["height"], k["width"]
    input_frame = o3d.t.pipelines.slam.Frame(height, width, intrinsic, device)
    raycast_frame = o3d.t.pipelines.slam.Frame(height, width, intrinsic, device)
    depth_scale = float(spec["depth_scale"])

    def depth_image(path: str):
        raw = np.asarray(o3d.t.io.read_image(path).as_tensor().numpy())
        raw = np.where(raw >= 65535, 0, raw).astype(np.uint16)  # 7-Scenes' original "no measurement"
        return o3d.t.geometry.Image(o3c.Tensor(raw)).to(device)

    poses, lost = [], 0
    started = time.perf_counter()
    for i, frame in enumerate(spec["frames"]):
        input_frame.set_data_from_image("depth", depth_image(frame["depth"]))
        input_frame.set_data_from_image("color", o3d.t.io.read_image(frame["rgb"]).to(device))
        if i > 0:
            result = model.track_frame_to_model(input_frame, raycast_frame, depth_scale, DEPTH_MAX, ODOMETRY_DISTANCE)
            if result.fitness < 0.1:
                lost += 1  # counted, as the example prints it; the pose is kept as Open3D returns it
            pose = pose @ result.transformation
        poses.append(pose.cpu().numpy())
        model.update_frame_pose(i, pose)
        model.integrate(input_frame, depth_scale, DEPTH_MAX, TRUNCATION_VOXELS)
        model.synthesize_model_frame(raycast_frame, depth_scale, DEPTH_MIN, DEPTH_MAX, TRUNCATION_VOXELS, False)
    seconds = time.perf_counter() - started
    np.save(out / "poses.npy", np.stack(poses))
    (out / "open3d.json").write_text(json.dumps({
        "open3d_version": o3d.__version__, "device": device_name, "frames": len(poses), "seconds": seconds,
        "seconds_per_frame": seconds / len(poses), "low_fitness_frames": lost, "voxel_size_m": VOXEL_SIZE,
        "depth_max_m": DEPTH_MAX, "block_count": BLOCK_COUNT,
    }, indent=2))


# --- steps 1 and 3, in this project's Python ------------------------------------------------------------------------


def write_frames(dataset, out: Path) -> None:
    import numpy as np

    records = dataset._records  # paths without reading the images
    first = dataset.gt_poses()[0]
    if first is None:  # ICL-NUIM's frame 1: start where the camera is; ATE aligns the two rigidly anyway
        print("the first frame has no reference pose: Open3D starts at the identity", flush=True)
        first = np.eye(4)
    i = dataset.intrinsics
    spec = {
        "intrinsics": {"width": i.width, "height": i.height, "fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy},
        "depth_scale": dataset.depth_scale,
        "first_pose": first.tolist(),
        "frames": [{"rgb": str(r.rgb_path), "depth": str(r.depth_path), "timestamp": r.timestamp} for r in records],
    }
    (out / "frames.json").write_text(json.dumps(spec))


def write_run_directory(dataset, out: Path, data: Path, frames: tuple) -> dict:
    """OUT as `eslam eval` reads a run: trajectory.txt, groundtruth.txt, summary.json."""
    import numpy as np

    from eslam_core.datasets.tum import write_tum
    from eslam_core.trajectory import Trajectory

    poses = np.load(out / "poses.npy")
    timing = json.loads((out / "open3d.json").read_text())
    timestamps = dataset.timestamps()
    write_tum(out / "trajectory.txt", Trajectory(timestamps, poses))
    reference = [(t, p) for t, p in zip(timestamps, dataset.gt_poses()) if p is not None]
    if reference:
        write_tum(out / "groundtruth.txt", Trajectory(np.array([t for t, _ in reference]),
                                                      np.stack([p for _, p in reference])))
    summary = {
        "data": str(data.resolve()), "dataset_kind": dataset.kind, "frames": list(frames), "n_frames": len(poses),
        "seconds": timing["seconds"], "seconds_per_frame": timing["seconds_per_frame"],
        "frames_per_second": 1.0 / timing["seconds_per_frame"], "peak_memory_mb": None, "parameter_count": None,
        "method": f"Open3D {timing['open3d_version']} t.pipelines.slam (voxel {1000 * VOXEL_SIZE:.2f} mm, "
                  f"depth_max {DEPTH_MAX:g} m)",
        "open3d": timing,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    if argv[:1] == ["slam"]:  # step 2, called by step 1 in Open3D's Python
        open3d_slam(Path(argv[1]), *(argv[2:3]))
        return 0
    sys.path.insert(0, str(HERE.parent.parent))
    from eslam_core.cli import parse_frames
    from eslam_core.datasets import open_dataset
    from eslam_core.evaluation.report import evaluate_run, write_report_json, write_report_markdown

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, type=Path)
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--kind", default="auto", help="data set kind (icl for ICL-NUIM), as dataset.kind")
    parser.add_argument("--frames", type=parse_frames, default=(0, None), help="A:B, frames to run (default all)")
    parser.add_argument("--open3d-python", default=OPEN3D_PYTHON, help="a Python with open3d installed")
    parser.add_argument("--device", default="CPU:0", help="Open3D device (CPU:0 or CUDA:0)")
    args = parser.parse_args(argv)

    frames = (args.frames[0], args.frames[1], 1)
    dataset = open_dataset(args.data, args.kind).subset(*frames)
    args.out.mkdir(parents=True, exist_ok=True)
    write_frames(dataset, args.out)
    print(f"Open3D dense SLAM on {len(dataset)} frames of {args.data} ...", flush=True)
    subprocess.run([args.open3d_python, str(HERE), "slam", str(args.out), args.device], check=True)
    summary = write_run_directory(dataset, args.out, args.data, frames)
    report = evaluate_run(args.out, depth_views=0)
    write_report_json(report, args.out / "report.json")
    write_report_markdown(report, args.out / "report.md")

    trajectory, consistency = report.get("trajectory") or {}, report.get("consistency") or {}
    per_metre = trajectory.get("rpe_per_metre") or {}
    estimate, reference = consistency.get("estimate") or {}, consistency.get("reference") or {}
    print(f"{summary['method']}: {summary['seconds_per_frame']:.3f} s/frame")
    print(f"ATE RMSE {trajectory.get('ate_rmse_cm', float('nan')):.2f} cm, RPE per metre "
          f"{per_metre.get('trans_rmse_cm', float('nan')):.2f} cm / {per_metre.get('rot_rmse_deg', float('nan')):.2f} "
          f"deg")
    print(f"depth consistency: Open3D poses {estimate.get('median_mm', float('nan')):.1f} mm "
          f"({estimate.get('agree_percent', float('nan')):.1f} % within 3 cm), reference poses "
          f"{reference.get('median_mm', float('nan')):.1f} mm ({reference.get('agree_percent', float('nan')):.1f} %)")
    print(f"report: {args.out / 'report.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
