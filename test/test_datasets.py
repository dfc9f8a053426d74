"""Data set readers, checked on tiny synthetic sequences of every format written into tmp_path."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from eslam_core.camera import Intrinsics, register_colour
from eslam_core.datasets import (
    DatasetError,
    ICLNUIMDataset,
    RGBDDataset,
    ReplicaDataset,
    ScanNetDataset,
    SevenScenesDataset,
    TUMDataset,
    detect_kind,
    open_dataset,
)
from eslam_core.datasets.read_ahead import ReadAhead
from eslam_core.datasets.tum import ICL_NUIM_INTRINSICS, associate_timestamps, nearest_within
from eslam_core.datasets.replica import REPLICA_INTRINSICS
from eslam_core.datasets.sevenscenes import SEVEN_SCENES_COLOUR_INTRINSICS, SEVEN_SCENES_INTRINSICS

W, H = 8, 6
SMALL = Intrinsics(W, H, fx=7.0, fy=7.5, cx=3.5, cy=2.5)


# --- writers of tiny synthetic data sets --------------------------------------------------------------------------


def random_pose(rng: np.random.Generator) -> np.ndarray:
    """A camera-to-world pose with a sizeable rotation and translation, so axis mistakes show."""
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    pose[:3, 3] = rng.uniform(-2.0, 2.0, size=3)
    return pose


def random_rgb(rng: np.random.Generator, width: int = W, height: int = H) -> np.ndarray:
    return rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)


def random_raw_depth(rng: np.random.Generator, scale: float, width: int = W, height: int = H) -> np.ndarray:
    """uint16 depth of 0.3-4 m with a few missing (0) pixels."""
    raw = np.round(rng.uniform(0.3, 4.0, size=(height, width)) * scale).astype(np.uint16)
    raw[rng.random((height, width)) < 0.2] = 0
    raw[0, 0] = 0
    return raw


def save_png16(path: Path, raw: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(raw.astype(np.uint16)).save(path)  # mode "I;16"


def save_rgb(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgb).save(path, quality=95)


def tum_line(t: float, pose: np.ndarray) -> str:
    qx, qy, qz, qw = Rotation.from_matrix(pose[:3, :3]).as_quat()
    tx, ty, tz = pose[:3, 3]
    return f"{t:.6f} {tx:.12f} {ty:.12f} {tz:.12f} {qx:.12f} {qy:.12f} {qz:.12f} {qw:.12f}"


def write_tum(root: Path, seed: int = 0, camera_json: bool = True) -> dict:
    """A TUM folder whose colour and depth clocks jitter by up to 15 ms.

    Colour at 1.0, 1.0333, 1.0667, 1.1 s and 2.0 s; the 2.0 s image has no depth within 20 ms and must be dropped.
    Ground truth exists within 20 ms of every kept frame except the third one.
    """
    rng = np.random.default_rng(seed)
    rgb_times = [1.0, 1.0 + 1 / 30, 1.0 + 2 / 30, 1.1, 2.0]
    depth_times = [1.004, 1.0 + 1 / 30 - 0.007, 1.0 + 2 / 30 + 0.012, 1.1 - 0.015, 2.05]
    rgbs, raws, poses = [], [], []
    for i, (tr, td) in enumerate(zip(rgb_times, depth_times)):
        rgbs.append(random_rgb(rng))
        raws.append(random_raw_depth(rng, 5000.0))
        poses.append(random_pose(rng))
        save_rgb(root / "rgb" / f"{tr:.6f}.png", rgbs[-1])
        save_png16(root / "depth" / f"{td:.6f}.png", raws[-1])
    header = "# colour images\n# file: 'synthetic'\n# timestamp filename\n"
    (root / "rgb.txt").write_text(header + "".join(f"{t:.6f} rgb/{t:.6f}.png\n" for t in rgb_times))
    # depth.txt deliberately out of time order: association must not depend on it
    order = [2, 0, 1, 4, 3]
    (root / "depth.txt").write_text(
        "# depth maps\n" + "".join(f"{depth_times[i]:.6f} depth/{depth_times[i]:.6f}.png\n" for i in order)
    )
    gt_lines = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for i in (0, 1, 3):
        gt_lines.append(tum_line(rgb_times[i] + 0.006, poses[i]))
    gt_lines.append(tum_line(rgb_times[2] + 0.05, random_pose(rng)))  # too far from frame 2 to be its pose
    (root / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    if camera_json:
        cam = {"width": W, "height": H, "fx": SMALL.fx, "fy": SMALL.fy, "cx": SMALL.cx, "cy": SMALL.cy,
               "depth_scale": 5000.0}
        (root / "camera.json").write_text(json.dumps(cam))
    kept = [0, 1, 2, 3]
    return {
        "times": [rgb_times[i] for i in kept],
        "rgb": [rgbs[i] for i in kept],
        "raw": [raws[i] for i in kept],
        "poses": [poses[0], poses[1], None, poses[3]],
    }


def write_icl(root: Path, seed: int = 1) -> dict:
    """ICL-NUIM in TUM layout: frames 1..3, `associations.txt` depth-first, ground truth only from frame 2."""
    rng = np.random.default_rng(seed)
    lines, gt_lines, raws, poses_file = [], [], [], {}
    for n in (1, 2, 3):
        save_rgb(root / "rgb" / f"{n}.png", random_rgb(rng))
        raws.append(random_raw_depth(rng, 5000.0))
        save_png16(root / "depth" / f"{n}.png", raws[-1])
        lines.append(f"{n} depth/{n}.png {n} rgb/{n}.png")
        if n >= 2:
            poses_file[n] = random_pose(rng)
            gt_lines.append(tum_line(n, poses_file[n]))
    (root / "associations.txt").write_text("\n".join(lines) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    return {"raw": raws, "poses_file": poses_file}


def write_replica(base: Path, seed: int = 2, cam_params: bool = True) -> dict:
    """Replica root with cam_params.json and scene office0: frames 0..2, traj.txt longer than the frames."""
    rng = np.random.default_rng(seed)
    scale = 1000.0 if cam_params else 6553.5  # a non-default scale proves cam_params.json is read
    results = base / "office0" / "results"
    rgbs, raws = [], []
    for k in range(3):
        # smooth colour: JPEG keeps it within a few levels, so the read can be compared with what was written
        y, x = np.mgrid[0:H, 0:W]
        rgb = np.stack([20 * x + 10 * k, 30 * y + 20, np.full_like(x, 128)], axis=-1).astype(np.uint8)
        rgbs.append(rgb)
        raws.append(random_raw_depth(rng, scale))
        save_rgb(results / f"frame{k:06d}.jpg", rgb)
        save_png16(results / f"depth{k:06d}.png", raws[-1])
    save_png16(results / "depth000007.png", random_raw_depth(rng, scale))  # no colour image: not a frame
    poses = [random_pose(rng) for _ in range(5)]
    (base / "office0" / "traj.txt").write_text(
        "".join(" ".join(f"{v:.18e}" for v in pose.reshape(-1)) + "\n" for pose in poses)
    )
    if cam_params:
        camera = {"w": W, "h": H, "fx": SMALL.fx, "fy": SMALL.fy, "cx": SMALL.cx, "cy": SMALL.cy, "scale": scale}
        (base / "cam_params.json").write_text(json.dumps({"camera": camera}))
    return {"rgb": rgbs, "raw": raws, "poses": poses[:3], "scale": scale}


def colour_at(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A colour linear in the (high-resolution) pixel coordinates, so a resize's geometry can be checked."""
    return np.stack([8.0 * x + 20, 12.0 * y + 30, 100 + 4.0 * x + 4.0 * y], axis=-1)


def write_scannet(scene: Path, seed: int = 3) -> dict:
    """ScanNet scene: frames 0, 2, 10 (numeric order differs from text order), colour twice the depth size,
    pose of frame 2 invalid (-inf), depth intrinsics in intrinsic/intrinsic_depth.txt."""
    rng = np.random.default_rng(seed)
    numbers = [0, 2, 10]
    raws, poses = [], []
    y, x = np.mgrid[0 : 2 * H, 0 : 2 * W].astype(np.float64)
    for k in numbers:
        save_rgb(scene / "color" / f"{k}.jpg", np.round(colour_at(x, y) + k).astype(np.uint8))
        raws.append(random_raw_depth(rng, 1000.0))
        save_png16(scene / "depth" / f"{k}.png", raws[-1])
        pose = random_pose(rng)
        if k == 2:
            pose = np.full((4, 4), -np.inf)
            poses.append(None)
        else:
            poses.append(pose)
        (scene / "pose").mkdir(parents=True, exist_ok=True)
        np.savetxt(scene / "pose" / f"{k}.txt", pose)
    (scene / "intrinsic").mkdir(parents=True, exist_ok=True)
    matrix = np.eye(4)
    matrix[0, 0], matrix[1, 1], matrix[0, 2], matrix[1, 2] = SMALL.fx, SMALL.fy, SMALL.cx, SMALL.cy
    np.savetxt(scene / "intrinsic" / "intrinsic_depth.txt", matrix)
    np.savetxt(scene / "intrinsic" / "intrinsic_color.txt", matrix * 2)  # must not be used
    return {"numbers": numbers, "raw": raws, "poses": poses}


def write_7scenes(seq: Path, seed: int = 4, colour_suffix: str = ".color.png", intrinsics_file: bool = False,
                  kinectfusion_rotations: bool = False) -> dict:
    """7-Scenes sequence folder with frames 0..2 and missing depth marked both ways (65535 and 0).

    `colour_suffix` ".color.jpg" writes the JPEG copy most people download (smooth colour, so that JPEG stays within
    a few levels); `intrinsics_file` writes a 3x3 camera-intrinsics.txt of SMALL; `kinectfusion_rotations` scales
    each rotation by 0.9999, as KinectFusion's poses are only orthonormal to about 1e-4.
    """
    rng = np.random.default_rng(seed)
    seq.mkdir(parents=True, exist_ok=True)
    rgbs, raws, poses = [], [], []
    for k in range(3):
        if colour_suffix == ".color.png":
            rgbs.append(random_rgb(rng))
        else:
            y, x = np.mgrid[0:H, 0:W]
            rgbs.append(np.stack([20 * x + 15 * k, 30 * y + 20, np.full_like(x, 90)], axis=-1).astype(np.uint8))
        raw = random_raw_depth(rng, 1000.0)  # includes 0 = missing
        raw[1, :3] = 65535
        raws.append(raw)
        poses.append(random_pose(rng))
        written = poses[-1].copy()
        if kinectfusion_rotations:
            written[:3, :3] *= 0.9999
        save_rgb(seq / f"frame-{k:06d}{colour_suffix}", rgbs[-1])
        save_png16(seq / f"frame-{k:06d}.depth.png", raw)
        np.savetxt(seq / f"frame-{k:06d}.pose.txt", written, fmt="%.12e")
    if intrinsics_file:
        np.savetxt(seq / "camera-intrinsics.txt", SMALL.matrix(), fmt="%.18e")
    return {"rgb": rgbs, "raw": raws, "poses": poses}


def metres(raw: np.ndarray, scale: float) -> np.ndarray:
    return raw.astype(np.float32) / np.float32(scale)


# --- TUM ----------------------------------------------------------------------------------------------------------


def test_tum_association_depth_poses_and_intrinsics(tmp_path):
    truth = write_tum(tmp_path / "synthetic_seq")
    ds = open_dataset(tmp_path / "synthetic_seq")
    assert isinstance(ds, TUMDataset) and ds.kind == "tum" and ds.name == "synthetic_seq"
    assert len(ds) == 4  # the 2.0 s colour image has no depth within 20 ms
    np.testing.assert_allclose(ds.timestamps(), truth["times"], atol=1e-6)  # written with 6 decimals
    assert ds.intrinsics == SMALL and ds.depth_scale == 5000.0
    for i, frame in enumerate(ds):
        assert frame.index == i
        assert frame.rgb.dtype == np.uint8 and frame.rgb.shape == (H, W, 3)
        np.testing.assert_array_equal(frame.rgb, truth["rgb"][i])  # the right image was paired, bit-exact (PNG)
        assert frame.depth.dtype == np.float32 and frame.depth.shape == (H, W)
        np.testing.assert_array_equal(frame.depth, metres(truth["raw"][i], 5000.0))
        assert frame.depth[0, 0] == 0.0
        if truth["poses"][i] is None:
            assert frame.pose is None
        else:
            np.testing.assert_allclose(frame.pose, truth["poses"][i], atol=1e-9)
    assert ds.has_ground_truth
    assert [p is None for p in ds.gt_poses()] == [False, False, True, False]


def test_association_prefers_the_closest_pair_and_uses_each_depth_once():
    def pairs(first, second):
        return associate_timestamps(np.asarray(first, dtype=float), np.asarray(second, dtype=float), 0.02).tolist()

    # colour at 0.0 and 0.015 both within 20 ms of the only depth (0.010): the nearer (0.015) gets it
    assert pairs([0.0, 0.015], [0.010]) == [[1, 0]]
    # regular 30 Hz streams offset by 10 ms pair one-to-one; offset by 25 ms, each depth pairs with the next
    # colour image (8.3 ms away) and the first colour image has none
    rgb = np.arange(10) / 30
    assert pairs(rgb, rgb + 0.010) == [[i, i] for i in range(10)]
    assert pairs(rgb, rgb + 0.025) == [[i + 1, i] for i in range(9)]
    assert pairs([0.0], [0.025]) == []
    # a list written out of time order comes back in time order; an exact 20 ms gap (printed decimals) pairs
    assert pairs([0.2, 0.1], [0.1, 0.22]) == [[1, 0], [0, 1]]
    # ground truth may be reused and is taken nearest-first
    np.testing.assert_array_equal(
        nearest_within(np.array([0.0, 0.011, 0.5]), np.array([0.02, 0.0, 0.01]), 0.02), [1, 2, -1]
    )


def test_tum_intrinsics_from_folder_name_argument_or_error(tmp_path):
    write_tum(tmp_path / "rgbd_dataset_freiburg2_xyz", camera_json=False)
    ds = open_dataset(tmp_path / "rgbd_dataset_freiburg2_xyz")
    assert (ds.intrinsics.fx, ds.intrinsics.fy, ds.intrinsics.cx, ds.intrinsics.cy) == (520.9, 521.0, 325.1, 249.7)
    assert (ds.intrinsics.width, ds.intrinsics.height) == (640, 480)
    with pytest.raises(DatasetError, match="intrinsics are for 640x480"):
        ds[0]  # the 8x6 images do not fit the Kinect calibration: caught, not silently mis-projected

    write_tum(tmp_path / "my_capture", camera_json=False)
    with pytest.raises(DatasetError, match="pass intrinsics"):
        open_dataset(tmp_path / "my_capture")
    ds = open_dataset(tmp_path / "my_capture", intrinsics=SMALL, depth_scale=1000.0)
    assert ds.intrinsics == SMALL and ds.depth_scale == 1000.0
    truth_raw = write_tum(tmp_path / "again")["raw"][1]
    np.testing.assert_array_equal(ds[1].depth, metres(truth_raw, 1000.0))

    other = Intrinsics(W, H, fx=9.0, fy=9.0, cx=4.0, cy=3.0)
    assert open_dataset(tmp_path / "again", intrinsics=other).intrinsics == other  # argument beats camera.json


# --- ICL-NUIM -----------------------------------------------------------------------------------------------------


def test_icl_flips_ground_truth_y_axis_and_uses_its_intrinsics(tmp_path):
    truth = write_icl(tmp_path / "icl")
    assert detect_kind(tmp_path / "icl") == "tum"  # ICL looks like TUM: it is only opened on request
    ds = open_dataset(tmp_path / "icl", "icl")
    assert isinstance(ds, ICLNUIMDataset) and ds.kind == "icl"
    assert ds.intrinsics == ICL_NUIM_INTRINSICS and ds.depth_scale == 5000.0
    np.testing.assert_array_equal(ds.timestamps(), [1.0, 2.0, 3.0])
    poses = ds.gt_poses()
    assert poses[0] is None  # ground truth starts at frame 2
    flip = np.diag([1.0, -1.0, 1.0, 1.0])
    for n in (2, 3):
        file_pose = truth["poses_file"][n]
        np.testing.assert_allclose(poses[n - 1], flip @ file_pose @ flip, atol=1e-9)
        # spelled out: y translation and the rotation entries coupling y with x or z change sign
        np.testing.assert_allclose(poses[n - 1][:3, 3], file_pose[:3, 3] * [1, -1, 1], atol=1e-9)
        sign = np.array([[1, -1, 1], [-1, 1, -1], [1, -1, 1]])
        np.testing.assert_allclose(poses[n - 1][:3, :3], file_pose[:3, :3] * sign, atol=1e-9)
        assert np.linalg.norm(poses[n - 1] - file_pose) > 0.1  # the flip really changed something

    small = open_dataset(tmp_path / "icl", "icl", intrinsics=SMALL)
    frame = small[2]
    assert frame.timestamp == 3.0
    np.testing.assert_array_equal(frame.depth, metres(truth["raw"][2], 5000.0))

    # ICL-NUIM's own downloads name the ground truth <scene>.gt.freiburg
    (tmp_path / "icl" / "groundtruth.txt").rename(tmp_path / "icl" / "office0.gt.freiburg")
    renamed = open_dataset(tmp_path / "icl", "icl").gt_poses()
    assert renamed[0] is None
    np.testing.assert_allclose(renamed[1], poses[1], atol=1e-12)


# --- Replica ------------------------------------------------------------------------------------------------------


def test_replica_root_or_scene_folder_cam_params_and_trajectory(tmp_path):
    truth = write_replica(tmp_path / "Replica")
    for path in (tmp_path / "Replica", tmp_path / "Replica" / "office0"):
        assert detect_kind(path) == "replica"
        ds = open_dataset(path)
        assert isinstance(ds, ReplicaDataset) and ds.name == "office0"
        assert ds.root == tmp_path / "Replica" / "office0"
        assert len(ds) == 3  # depth000007.png has no colour image
        assert ds.intrinsics == SMALL and ds.depth_scale == truth["scale"]
        np.testing.assert_array_equal(ds.timestamps(), [0.0, 1.0, 2.0])
        for i, frame in enumerate(ds):
            assert frame.rgb.dtype == np.uint8 and frame.rgb.shape == (H, W, 3)
            assert np.abs(frame.rgb.astype(int) - truth["rgb"][i]).mean() < 4  # JPEG, within a few levels
            np.testing.assert_array_equal(frame.depth, metres(truth["raw"][i], truth["scale"]))
            np.testing.assert_allclose(frame.pose, truth["poses"][i], atol=1e-12)


def test_replica_defaults_without_cam_params(tmp_path):
    write_replica(tmp_path / "Replica", cam_params=False)
    ds = open_dataset(tmp_path / "Replica" / "office0", "replica")
    assert ds.intrinsics == REPLICA_INTRINSICS and ds.depth_scale == 6553.5
    assert ds.mesh_path is None
    (tmp_path / "Replica" / "office0_mesh.ply").write_text("ply\n")
    assert ds.mesh_path == tmp_path / "Replica" / "office0_mesh.ply"


# --- ScanNet ------------------------------------------------------------------------------------------------------


def test_scannet_numeric_order_resized_colour_invalid_pose(tmp_path):
    truth = write_scannet(tmp_path / "scene0000_00")
    assert detect_kind(tmp_path / "scene0000_00") == "scannet"
    ds = open_dataset(tmp_path / "scene0000_00")
    assert isinstance(ds, ScanNetDataset) and ds.name == "scene0000_00"
    assert ds.intrinsics == SMALL and ds.depth_scale == 1000.0  # of depth, not colour
    np.testing.assert_allclose(ds.timestamps(), np.array([0, 2, 10]) / 30)
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    for i, frame in enumerate(ds):
        k = truth["numbers"][i]
        assert frame.rgb.dtype == np.uint8 and frame.rgb.shape == (H, W, 3)
        # a depth pixel's centre (u, v) lies at (2u + 0.5, 2v + 0.5) in the colour image of twice the size
        expected = colour_at(2 * x + 0.5, 2 * y + 0.5) + k
        inner = (slice(1, -1), slice(1, -1))  # borders are clamped by the resampling filter
        assert np.abs(frame.rgb[inner] - expected[inner]).mean() < 3.0
        np.testing.assert_array_equal(frame.depth, metres(truth["raw"][i], 1000.0))
        if truth["poses"][i] is None:
            assert frame.pose is None
        else:
            np.testing.assert_allclose(frame.pose, truth["poses"][i], atol=1e-12)
    assert [p is None for p in ds.gt_poses()] == [False, True, False]


def test_scannet_nice_slam_frames_layout_and_missing_intrinsics(tmp_path):
    write_scannet(tmp_path / "scene0001_00" / "frames")
    assert detect_kind(tmp_path / "scene0001_00") == "scannet"
    ds = open_dataset(tmp_path / "scene0001_00")
    assert len(ds) == 3 and ds.name == "scene0001_00"
    (tmp_path / "scene0001_00" / "frames" / "intrinsic" / "intrinsic_depth.txt").unlink()
    with pytest.raises(DatasetError, match="intrinsic_depth.txt"):
        open_dataset(tmp_path / "scene0001_00")
    assert open_dataset(tmp_path / "scene0001_00", intrinsics=SMALL).intrinsics == SMALL


# --- 7-Scenes -----------------------------------------------------------------------------------------------------


def test_7scenes_invalid_depth_poses_defaults(tmp_path):
    truth = write_7scenes(tmp_path / "chess" / "seq-01")
    assert detect_kind(tmp_path / "chess" / "seq-01") == "7scenes"
    ds = open_dataset(tmp_path / "chess" / "seq-01")
    assert isinstance(ds, SevenScenesDataset) and ds.name == "chess-seq-01"
    assert ds.intrinsics == SEVEN_SCENES_INTRINSICS and ds.depth_scale == 1000.0
    np.testing.assert_allclose(ds.timestamps(), np.arange(3) / 30)
    ds = open_dataset(tmp_path / "chess" / "seq-01", intrinsics=SMALL)
    for i, frame in enumerate(ds):
        np.testing.assert_array_equal(frame.rgb, truth["rgb"][i])
        np.testing.assert_array_equal(frame.depth, seven_scenes_depth(truth["raw"][i]))
        assert np.all(frame.depth[1, :3] == 0.0) and frame.depth.max() < 4.01
        np.testing.assert_allclose(frame.pose, truth["poses"][i], atol=1e-11)
    # a scene folder is recognised, and the user is told which sequence folders to pass
    assert detect_kind(tmp_path / "chess") == "7scenes"
    with pytest.raises(DatasetError, match="seq-01"):
        open_dataset(tmp_path / "chess")


def seven_scenes_depth(raw: np.ndarray) -> np.ndarray:
    expected = metres(raw, 1000.0)
    expected[raw == 65535] = 0.0
    return expected


def test_7scenes_jpeg_copy_with_intrinsics_file_and_kinectfusion_poses(tmp_path):
    # the copy widely downloaded: one flat folder, JPEG colour, camera-intrinsics.txt, 0 for missing depth
    folder = tmp_path / "7scenes_redkitchen_0_2"
    truth = write_7scenes(folder, colour_suffix=".color.jpg", intrinsics_file=True, kinectfusion_rotations=True)
    assert detect_kind(folder) == "7scenes"
    ds = open_dataset(folder)
    assert isinstance(ds, SevenScenesDataset) and ds.name == "7scenes_redkitchen_0_2" and len(ds) == 3
    assert ds.intrinsics == SMALL  # from camera-intrinsics.txt (3x3), sized by the depth images
    for i, frame in enumerate(ds):
        assert frame.rgb.dtype == np.uint8 and frame.rgb.shape == (H, W, 3)
        assert np.abs(frame.rgb.astype(int) - truth["rgb"][i]).mean() < 4  # JPEG, within a few levels
        np.testing.assert_array_equal(frame.depth, seven_scenes_depth(truth["raw"][i]))
        assert np.all(frame.depth[truth["raw"][i] == 0] == 0.0) and np.all(frame.depth[1, :3] == 0.0)
        rotation = frame.pose[:3, :3]
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)  # re-orthonormalised
        assert np.linalg.det(rotation) > 0
        np.testing.assert_allclose(frame.pose, truth["poses"][i], atol=2e-4)  # the nearest rotation: the true one
        np.testing.assert_allclose(frame.pose[:3, 3], truth["poses"][i][:3, 3], atol=1e-11)

    # the intrinsics argument (config `camera:`) wins over the file
    other = Intrinsics(W, H, fx=9.0, fy=9.0, cx=4.0, cy=3.0)
    assert open_dataset(folder, intrinsics=other).intrinsics == other
    (folder / "camera-intrinsics.txt").write_text("585 0 320\n0 585 240\n")
    with pytest.raises(DatasetError, match=r"camera-intrinsics\.txt: expected 3 lines of 3 numbers"):
        open_dataset(folder)


def test_7scenes_jpeg_sequences_in_a_scene_folder_and_png_preferred(tmp_path):
    scene = tmp_path / "redkitchen"
    truth = write_7scenes(scene / "seq-01", colour_suffix=".color.jpg")
    np.savetxt(scene / "camera-intrinsics.txt", SMALL.matrix())  # the scene folder's file serves its sequences
    assert detect_kind(scene) == "7scenes" and detect_kind(scene / "seq-01") == "7scenes"
    with pytest.raises(DatasetError, match="seq-01"):
        open_dataset(scene)
    ds = open_dataset(scene / "seq-01")
    assert ds.name == "redkitchen-seq-01" and ds.intrinsics == SMALL
    assert [r.rgb_path.name for r in ds._records] == [f"frame-{k:06d}.color.jpg" for k in range(3)]
    # where a frame has both, the lossless PNG is read
    png = random_rgb(np.random.default_rng(9))
    save_rgb(scene / "seq-01" / "frame-000001.color.png", png)
    ds = open_dataset(scene / "seq-01")
    assert len(ds) == 3
    np.testing.assert_array_equal(ds[1].rgb, png)
    assert np.abs(ds[2].rgb.astype(int) - truth["rgb"][2]).mean() < 4
    # no colour in either form: the error names both
    for child in (scene / "seq-01").glob("*.color.*"):
        child.unlink()
    with pytest.raises(DatasetError, match=r"no RGB-D frames.*\.color\.png \(or \.color\.jpg\)"):
        open_dataset(scene / "seq-01", "7scenes")


def _texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth colour pattern on the plane z = const, as a function of its metric coordinates (x, y)."""
    return np.stack([128 + 100 * np.sin(9 * x), 128 + 100 * np.cos(7 * y), 128 + 60 * np.sin(5 * (x + y))],
                    -1).astype(np.uint8)


def _plane_seen_by(intr: Intrinsics, z: float, centre: np.ndarray = np.zeros(3)) -> np.ndarray:
    """The image of the textured plane z (world = depth camera frame) taken by a camera at `centre`, same axes."""
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
    depth = z - centre[2]
    return _texture((u - intr.cx) / intr.fx * depth + centre[0], (v - intr.cy) / intr.fy * depth + centre[1])


def test_colour_registration_resamples_the_colour_camera_onto_the_depth_pixels():
    depth_camera = Intrinsics(64, 48, fx=58.5, fy=58.5, cx=32.0, cy=24.0)
    colour_camera = Intrinsics(64, 48, fx=52.5, fy=52.5, cx=31.0, cy=24.5)
    z, baseline = 1.5, np.array([-0.025, 0.0, 0.0])  # the colour camera 2.5 cm beside the depth camera
    depth = np.full((48, 64), z, np.float32)
    truth = _plane_seen_by(depth_camera, z).astype(int)
    depth_to_colour = np.eye(4)
    depth_to_colour[:3, 3] = -baseline
    shot = _plane_seen_by(colour_camera, z, baseline)
    registered = register_colour(shot, depth, depth_camera, colour_camera, depth_to_colour).astype(int)
    inner = np.s_[4:-4, 4:-4]  # the colour camera's wider view covers these; the edges are extrapolated
    assert np.abs(registered - truth)[inner].mean() < 3
    assert np.abs(shot.astype(int) - truth)[inner].mean() > 10  # as shot, the pixels see other points
    # Without depth a pixel is taken at infinity, where only the rotation counts: exact for cameras sharing a centre.
    same_centre = register_colour(_plane_seen_by(colour_camera, z), np.zeros_like(depth), depth_camera, colour_camera)
    assert np.abs(same_centre.astype(int) - truth)[inner].mean() < 3


def test_7scenes_colour_is_registered_to_depth_as_read(tmp_path):
    """Frames of the shipped size get their colour resampled from the 525-pixel colour camera onto the 585-pixel
    depth camera; dataset.register_colour false keeps it as shipped."""
    folder = tmp_path / "seq-01"
    folder.mkdir()
    z = 2.0
    shot = _plane_seen_by(SEVEN_SCENES_COLOUR_INTRINSICS, z)
    save_rgb(folder / "frame-000000.color.png", shot)
    save_png16(folder / "frame-000000.depth.png", np.full((480, 640), int(z * 1000), np.uint16))
    truth = _plane_seen_by(SEVEN_SCENES_INTRINSICS, z).astype(int)
    registered = open_dataset(folder)[0].rgb.astype(int)
    assert np.abs(registered - truth).mean() < 2
    as_shipped = open_dataset(folder, register_colour=False)[0].rgb
    np.testing.assert_array_equal(as_shipped, shot)
    assert np.abs(as_shipped.astype(int) - truth).mean() > 20


def test_scannet_zero_padded_png_export_keeps_its_poses(tmp_path):
    scene = tmp_path / "scene0002_00"
    truth = write_scannet(scene)
    for folder, suffix in (("color", ".jpg"), ("depth", ".png"), ("pose", ".txt")):
        for k in truth["numbers"]:
            (scene / folder / f"{k}{suffix}").rename(scene / folder / f"{k:06d}{suffix}")
    for k in truth["numbers"]:  # colour as PNG, as some exporters write it
        jpg = scene / "color" / f"{k:06d}.jpg"
        Image.open(jpg).save(jpg.with_suffix(".png"))
        jpg.unlink()
    ds = open_dataset(scene)
    assert len(ds) == 3
    np.testing.assert_allclose(ds.timestamps(), np.array(truth["numbers"]) / 30)
    assert [p is None for p in ds.gt_poses()] == [False, True, False]  # poses found despite the padding
    np.testing.assert_allclose(ds.gt_poses()[2], truth["poses"][2], atol=1e-12)
    np.testing.assert_array_equal(ds[2].depth, metres(truth["raw"][2], 1000.0))


def test_rotations_that_are_not_rotations_are_refused(tmp_path):
    seq = tmp_path / "seq-01"
    write_7scenes(seq)
    mirrored = np.diag([1.0, 1.0, -1.0, 1.0])  # orthonormal but a reflection
    np.savetxt(seq / "frame-000001.pose.txt", mirrored)
    with pytest.raises(DatasetError, match=r"frame-000001\.pose\.txt: not a rigid"):
        open_dataset(seq)


# --- the Sequence behaviour and subset() ----------------------------------------------------------------------------


def seven_frames(seq: Path) -> dict:
    """7-Scenes frames 0-6 in `seq` (poses for frames 0-2 only): `write_7scenes`'s truth, colour of all seven."""
    truth = write_7scenes(seq)
    for k in range(3, 7):
        truth["rgb"].append(random_rgb(np.random.default_rng(k)))
        save_rgb(seq / f"frame-{k:06d}.color.png", truth["rgb"][-1])
        save_png16(seq / f"frame-{k:06d}.depth.png", random_raw_depth(np.random.default_rng(k), 1000.0))
    return truth


def test_indexing_iteration_and_subset_views(tmp_path):
    truth = seven_frames(tmp_path / "seq-01")
    ds = open_dataset(tmp_path / "seq-01", intrinsics=SMALL)
    assert isinstance(ds, RGBDDataset) and len(ds) == 7
    assert ds[-1].timestamp == pytest.approx(6 / 30) and ds[-7].timestamp == 0.0
    with pytest.raises(IndexError):
        ds[7]
    with pytest.raises(IndexError):
        ds[-8]
    assert len(list(ds)) == 7
    assert ds.gt_poses()[5] is None and ds.has_ground_truth  # frames 3..6 have no pose file

    view = ds.subset(1, 6, 2)  # frames 1, 3, 5
    assert len(view) == 3 and view.kind == "7scenes" and view.intrinsics == SMALL
    np.testing.assert_allclose(view.timestamps(), np.array([1, 3, 5]) / 30)
    assert view[0].index == 0  # indices are positions in the view
    np.testing.assert_array_equal(view[0].rgb, truth["rgb"][1])
    np.testing.assert_allclose(view.gt_poses()[0], truth["poses"][1])
    assert [p is None for p in view.gt_poses()] == [False, True, True]
    assert len(ds) == 7  # the original is untouched
    assert view.subset(stride=2).timestamps() * 30 == pytest.approx([1, 5])
    assert ds.subset(start=5).timestamps() * 30 == pytest.approx([5, 6])
    assert not ds.subset(start=3).has_ground_truth
    with pytest.raises(DatasetError, match="stride"):
        ds.subset(stride=0)
    with pytest.raises(DatasetError, match="selects no frames"):
        ds.subset(start=9)

    pose = ds[0].pose
    pose[:] = 0.0  # frames hand out copies: the data set's poses cannot be corrupted by a caller
    np.testing.assert_allclose(ds[0].pose, truth["poses"][0])


def test_read_ahead_hands_out_the_frames_it_read_before_and_reads_at_most_its_capacity(tmp_path):
    rgbs = seven_frames(tmp_path / "seq-01")["rgb"]
    ds = open_dataset(tmp_path / "seq-01", intrinsics=SMALL)
    with ReadAhead(ds, capacity=3) as frames:
        assert frames.ready == 0  # nothing is read before the first frame is taken
        np.testing.assert_array_equal(frames[0].rgb, rgbs[0])
        deadline = time.monotonic() + 30.0
        while frames.ready < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.2)
        assert frames.ready == 3  # frames 1-3, and no further
        for image in (tmp_path / "seq-01").glob("*.png"):
            image.unlink()
        for k in (1, 2, 3):  # from memory: their files are gone
            frame = frames[k]
            assert frame.index == k
            np.testing.assert_array_equal(frame.rgb, rgbs[k])
        with pytest.raises(DatasetError, match="frame-000004"):  # not read ahead: the caller's own read fails
            frames[4]
        assert frames.read_ahead == 3
    assert frames.ready == 0  # closing drops what was read ahead


def test_read_ahead_gives_the_right_frames_when_the_caller_jumps_ahead(tmp_path):
    rgbs = seven_frames(tmp_path / "seq-01")["rgb"]
    ds = open_dataset(tmp_path / "seq-01", intrinsics=SMALL)
    with ReadAhead(ds, capacity=2) as frames:
        for k in (0, 4, 5, 6):
            np.testing.assert_array_equal(frames[k].rgb, rgbs[k])
    with pytest.raises(ValueError, match="capacity"):
        ReadAhead(ds, capacity=0)


# --- detection and errors -----------------------------------------------------------------------------------------


def test_detection_failures_name_what_was_looked_for(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError) as err:
        detect_kind(tmp_path / "empty")
    for clue in ("cam_params.json", "color/", "frame-*.color.png", "rgb.txt", "associations.txt"):
        assert clue in str(err.value)
    with pytest.raises(DatasetError, match="not found"):
        open_dataset(tmp_path / "nowhere")
    with pytest.raises(DatasetError, match="unknown data set kind"):
        open_dataset(tmp_path / "empty", "kitti")
    assert issubclass(DatasetError, ValueError)


def test_missing_and_malformed_files_are_named(tmp_path):
    root = tmp_path / "seq"
    write_tum(root)

    (root / "groundtruth.txt").write_text("# comment\n1.0 0 0 0 0 0 0 1\n1.1 0 0 zero 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"groundtruth\.txt, line 3"):
        open_dataset(root)
    (root / "groundtruth.txt").write_text("1.0 0 0 0 0 0 0 1\n1.1 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"groundtruth\.txt, line 2: expected 8 fields"):
        open_dataset(root)
    (root / "groundtruth.txt").unlink()  # optional: frames simply have no pose
    assert not open_dataset(root).has_ground_truth

    (root / "rgb.txt").write_text("1.0 rgb/1.000000.png\nbad line with four\n")
    with pytest.raises(DatasetError, match=r"rgb\.txt, line 2"):
        open_dataset(root)
    (root / "rgb.txt").write_text("# nothing but comments\n")
    with pytest.raises(DatasetError, match="no RGB-D frames"):
        open_dataset(root)
    (root / "rgb.txt").write_text("5.0 rgb/1.000000.png\n")
    with pytest.raises(DatasetError, match="within 0.02 s"):
        open_dataset(root)

    (root / "depth.txt").unlink()
    with pytest.raises(DatasetError) as err:
        open_dataset(root, "tum")
    assert str(root / "depth.txt") in str(err.value)

    replica = tmp_path / "Replica"
    write_replica(replica)
    traj = replica / "office0" / "traj.txt"
    traj.write_text(traj.read_text().splitlines()[0] + "\n1 0 0\n")
    with pytest.raises(DatasetError, match=r"traj\.txt, line 2"):
        open_dataset(replica)


def test_lazy_image_errors_are_raised_at_getitem(tmp_path):
    root = tmp_path / "seq"
    write_tum(root)
    ds = open_dataset(root)
    listed = (root / "rgb.txt").read_text().splitlines()[3].split()[1]

    (root / listed).unlink()
    with pytest.raises(DatasetError) as err:
        ds[0]
    assert str(root / listed) in str(err.value)

    (root / listed).write_bytes(b"\x89PNG not really an image")
    with pytest.raises(DatasetError, match="corrupt"):
        ds[0]

    save_rgb(root / listed, random_rgb(np.random.default_rng(0), width=W + 2))
    with pytest.raises(DatasetError, match="register"):
        ds[0]  # colour 10x6, depth 8x6

    depth_file = next((root / "depth").glob("1.004000.png"))
    save_rgb(root / listed, random_rgb(np.random.default_rng(0)))
    Image.fromarray(np.full((H, W), 7, dtype=np.uint8)).save(depth_file)  # 8-bit depth
    with pytest.raises(DatasetError, match="16-bit"):
        ds[0]
    assert ds[1].depth.shape == (H, W)  # other frames still load
