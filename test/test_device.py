"""The same method on any device (`run.device`): lookups, rendering, mapping, tracking and the shared map of the
pipelined runtime run on the `device` fixture's device (the CPU always, a CUDA GPU when torch sees one) and give
the CPU's results; a config asking for a GPU the machine lacks stops with one clear line."""
import sys

import numpy as np
import pytest
import torch
import torch.multiprocessing as tmp

from eslam_core.cli import main
from eslam_core.config import ConfigError, RenderConfig, load_config
from eslam_core.device import device_problem, resolve_device
from eslam_core.frames import pixel_directions_table, prepare_frame
from eslam_core.geometry import rotation_angle_deg
from eslam_core.mapping.extent import grow_to_multiple
from eslam_core.mapping.keyframes import Keyframe
from eslam_core.mapping.mapper import Mapper
from eslam_core.mapping.observed import ObservedSpace
from eslam_core.representation.field import SceneField
from eslam_core.representation.planes import FeaturePlanes, reference_lookup
from eslam_core.rendering.volume import render_rays
from eslam_core.runtime.shared import MapMeta, SharedMap
from eslam_core.tracking.render_tracker import Tracker
from eslam_core.tracking.sdf_tracker import SDFTracker

ROOM_BOUND = np.array([[-2.1, -1.6, -0.1], [2.1, 1.6, 2.7]])


@pytest.fixture(params=["cpu", "cuda"], scope="module")
def device(request):
    if request.param == "cuda" and not torch.cuda.is_available():
        pytest.skip("no CUDA GPU visible to torch")
    return torch.device(request.param, 0) if request.param == "cuda" else torch.device("cpu")


def rotation(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.radians(deg)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def pose_errors(est: torch.Tensor, gt: np.ndarray) -> tuple[float, float]:
    e = est.double().numpy()
    return float(np.linalg.norm(e[:3, 3] - gt[:3, 3])), rotation_angle_deg(e[:3, :3].T @ gt[:3, :3])


# ---------------------------------------------------------------------------------------------- representation

def test_lookup_on_the_device_equals_the_cpu_lookup(device):
    """Features and their gradients (table and points) on the device are the CPU's (the fused kernel's there)."""
    bound = np.array([[-1.0, -0.5, 0.0], [1.0, 0.7, 1.5]])
    torch.manual_seed(1)
    cpu = FeaturePlanes(bound, (0.24, 0.06), 8, 0.1)
    torch.manual_seed(1)
    dev = FeaturePlanes(bound, (0.24, 0.06), 8, 0.1, device=device)
    assert dev.table.device == device and torch.equal(dev.table.cpu(), cpu.table.detach())
    points = torch.rand(500, 3) * torch.tensor([2.4, 1.6, 1.9]) - torch.tensor([1.2, 0.7, 0.2])  # some outside
    p_cpu, p_dev = points.clone().requires_grad_(True), points.to(device).requires_grad_(True)
    f_cpu, f_dev = cpu(p_cpu), dev(p_dev)
    assert f_dev.device == device
    torch.testing.assert_close(f_dev.cpu(), f_cpu.detach(), atol=1e-5, rtol=1e-5)
    weights = torch.randn_like(f_cpu)
    (f_cpu * weights).sum().backward()
    (f_dev * weights.to(device)).sum().backward()
    torch.testing.assert_close(dev.table.grad.cpu(), cpu.table.grad, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(p_dev.grad.cpu(), p_cpu.grad, atol=1e-4, rtol=1e-4)
    # The plain-torch path on the CPU is the reference both agree with.
    ref = reference_lookup(points, cpu.table.detach(), cpu.bound_min, cpu.bound_extent, cpu.layout)
    torch.testing.assert_close(f_dev.detach().cpu(), ref, atol=1e-5, rtol=1e-5)


def test_grown_field_stays_on_its_device(device):
    cfg = load_config("demo")
    field = SceneField(grow_to_multiple(ROOM_BOUND, 0.24), cfg.model, device)
    extent = field.bound.copy()
    extent[0, 0] -= 0.48  # two coarse cells, as a map grows
    extent[1, 2] += 0.24
    grown = field.grown(extent)
    assert {p.device for p in grown.parameters()} == {device}
    p = torch.tensor([[0.3, 0.2, 1.1]])
    torch.testing.assert_close(grown.sdf(p), field.sdf(p))  # host points are answered on the field's device


def test_observed_space_on_the_device(device):
    space = ObservedSpace(np.array([[-1.0, -1.0, 0.0], [1.0, 1.0, 2.0]]), 0.06, device)
    g = torch.linspace(-0.3, 0.3, 40)
    wall = torch.stack(torch.meshgrid(g, g, indexing="ij") + (torch.full((40, 40), 1.5),), -1).reshape(-1, 3)
    space.add(wall)  # from the host
    queries = torch.tensor([[0.0, 0.0, 1.5], [0.1, -0.2, 1.56], [0.0, 0.0, 1.3], [0.8, 0.8, 1.5], [5.0, 0.0, 1.5],
                            [-5.0, -5.0, -5.0]], device=device)
    inside = space.contains(queries)
    assert inside.device == device and inside.tolist() == [True, True, False, False, False, False]


# --------------------------------------------------------------------------------------------------- rendering

class Wall:
    """A field whose TSDF is the distance to the wall z = 2 (truncated, normalised), on `device`."""

    def __init__(self, device, truncation=0.06):
        self.T = truncation
        self.beta = torch.tensor(40.0, device=device)
        self.bound_min = torch.tensor([-3.0, -3.0, -1.0], device=device)
        self.bound_max = torch.tensor([3.0, 3.0, 5.0], device=device)

    def sdf(self, p):
        return ((2.0 - p[:, 2]) / self.T).clamp(-1, 1)

    def color(self, p):
        return torch.stack([torch.full_like(p[:, 0], 0.25), (p[:, 0] > 0).float(), torch.full_like(p[:, 0], 0.75)], -1)


@pytest.mark.parametrize("with_depth", [True, False])
def test_render_on_the_device_finds_the_wall(device, with_depth):
    """Rays with depth (near-surface samples) and without (importance samples) render the wall's depth."""
    g = torch.linspace(-0.3, 0.3, 20)
    x, y = torch.meshgrid(g, g, indexing="ij")
    dirs = torch.stack([x.reshape(-1), y.reshape(-1), torch.ones(x.numel())], -1).to(device)
    origins = torch.zeros_like(dirs)
    depth = torch.full((len(dirs),), 2.0 if with_depth else 0.0, device=device)
    cfg = RenderConfig(n_importance=32) if with_depth else RenderConfig(n_stratified=48, n_importance=16)
    out = render_rays(Wall(device), origins, dirs, depth, cfg, 0.06)
    assert out.depth.device == device
    error = (out.depth - 2.0).abs()
    if with_depth:
        assert float(error.max()) < 0.01
    else:  # the surface found by importance sampling, most rays within 2 cm
        assert float(error.median()) < 0.02
    torch.testing.assert_close(out.color[:, 2].cpu(), torch.full((len(dirs),), 0.75), atol=0.02, rtol=0)


# ------------------------------------------------------------------------------------------ mapping, tracking

@pytest.fixture(scope="module")
def fitted(device, room_sequence):
    """A map of the synthetic room fitted on the device to keyframes 0, 6, 12 at their true poses (keyframes in
    host memory, as the keyframe store keeps them)."""
    torch.manual_seed(0)
    cfg = load_config("demo", {"mapping": {"rays": 1000, "first_iterations": 100}, "run": {"device": str(device)}})
    ds = room_sequence
    field = SceneField(grow_to_multiple(ROOM_BOUND, cfg.model.coarse_resolution), cfg.model, device)
    dirs = pixel_directions_table(ds.intrinsics)
    keyframes = []
    for i in (0, 6, 12):
        f = prepare_frame(ds[i], ds.intrinsics, cfg.camera)
        keyframes.append(Keyframe.from_tensors(i, f.timestamp, f.rgb, f.depth, f.depth >= 0,
                                               torch.from_numpy(f.gt_pose).float()))
    mapper = Mapper.of(cfg, dirs, ds.intrinsics.height, ds.intrinsics.width)
    result = mapper.map(field, keyframes, [0, 1, 2], first=True)
    return cfg, field, dirs, keyframes, result


def test_mapping_step_on_the_device(fitted, device):
    """Parameters stay on the device, keyframes on the host; the fitted map renders the keyframe's depth."""
    cfg, field, dirs, keyframes, result = fitted
    assert np.isfinite(result.loss)
    assert {p.device for p in field.parameters()} == {device}
    assert all(kf.rgb.device.type == "cpu" and kf.pose.device.type == "cpu" for kf in keyframes)
    kf = keyframes[1]
    pix = torch.nonzero(kf.depth_image().reshape(-1) > 0).squeeze(1)[::37]
    pose = kf.pose.to(device)
    rays = dirs[pix].to(device)
    depth = kf.depths(pix).to(device)
    out = render_rays(field, pose[:3, 3].expand(len(pix), 3), rays @ pose[:3, :3].T, depth, cfg.render,
                      cfg.model.truncation)
    assert float((out.depth.detach() - depth).abs().median()) < 0.03  # metres, after 100 iterations


def test_joint_pose_refinement_returns_host_poses(fitted, device):
    cfg, field, dirs, keyframes, _ = fitted
    cfg.mapping.iterations = 3
    mapper = Mapper.of(cfg, dirs, keyframes[0].rgb.shape[0], keyframes[0].rgb.shape[1])
    state = {k: v.clone() for k, v in field.state_dict().items()}
    try:
        result = mapper.map(field, keyframes, [0, 1, 2], optimise_poses=True)
    finally:
        field.load_state_dict(state)  # the other tests use the fitted map as it was
    assert sorted(result.refined) == [1, 2]  # the oldest anchors the gauge
    for i, pose in result.refined.items():
        assert pose.device.type == "cpu"
        assert float((pose - keyframes[i].pose).abs().max()) < 0.01  # a few small steps from the true pose


def perturbed_frame(cfg, room_sequence, index=9):
    frame = prepare_frame(room_sequence[index], room_sequence.intrinsics, cfg.camera)
    start = frame.gt_pose.copy()
    start[:3, :3] = rotation([0.3, 1.0, -0.2], 2.0) @ start[:3, :3]
    start[:3, 3] += np.array([0.015, -0.01, 0.01])  # 2 cm
    return frame, torch.from_numpy(start).float()


def test_tracking_step_on_the_device(fitted, device, room_sequence):
    """The paper's tracker on the device: from 2 cm / 2 degrees to under 1 cm / 0.5 degrees; the pose comes back
    to the host."""
    cfg, field, dirs, _, _ = fitted
    cfg.tracking.iterations, cfg.tracking.rays = 40, 1000
    cfg.render_tracker.lr_translation, cfg.render_tracker.lr_rotation = 0.003, 0.002
    frame, start = perturbed_frame(cfg, room_sequence)
    ds = room_sequence
    result = Tracker.of(cfg, dirs, ds.intrinsics.height, ds.intrinsics.width).track(field, frame, start)
    assert result.pose.device.type == "cpu" and np.isfinite(result.loss)
    t_err, r_err = pose_errors(result.pose, frame.gt_pose)
    assert t_err < 0.01 and r_err < 0.5, (t_err, r_err)


def test_sdf_tracking_on_the_device(fitted, device, room_sequence):
    """The fast tracker (SDF, map colour and the keyframe's images) on the device converges from 2 cm too."""
    cfg, field, dirs, keyframes, _ = fitted
    cfg.tracking.iterations, cfg.tracking.rays, cfg.sdf_tracker.color_weight = 15, 2000, 1.0
    frame, start = perturbed_frame(cfg, room_sequence)
    tracker = SDFTracker.of(cfg, dirs, room_sequence.intrinsics)
    result = tracker.track(field, frame, start, keyframe=keyframes[1])
    assert tracker._reference.depth.device == device
    assert result.pose.device.type == "cpu"
    t_err, r_err = pose_errors(result.pose, frame.gt_pose)
    assert t_err < 0.01 and r_err < 0.5, (t_err, r_err)


# ---------------------------------------------------------------------------------------- the shared map

def _reader(buffers, generation, meta, extent, model_cfg, device, answers):
    """Another process: attach to the shared map, copy it into a field of its own on the device, answer with a
    decoded value and the parameter sum."""
    field = SceneField(extent, model_cfg, device)
    shared = SharedMap(meta, buffers, generation)
    version = shared.read_into(field, -1)
    answers.put((version, float(field.sdf(torch.tensor([[0.2, 0.1, 1.0]])).detach()),
                 float(sum(p.detach().double().sum() for p in field.parameters()))))


def test_shared_map_between_processes_on_the_device(device):
    """The pipelined runtime's map exchange: the mapper's buffers on its field's device (shared memory on the CPU,
    CUDA IPC on a GPU), handed through a torch.multiprocessing queue to a spawned reader."""
    cfg = load_config("demo")
    extent = grow_to_multiple(np.array([[-1.0, -1.0, 0.0], [1.0, 1.0, 2.0]]), cfg.model.coarse_resolution)
    ctx = tmp.get_context("spawn")
    meta = MapMeta(ctx)
    field = SceneField(extent, cfg.model, device)
    shared = SharedMap.create(meta, field)
    assert shared.buffers.device == device
    with torch.no_grad():
        field.geometry_planes.table.add_(0.5)  # not the reader's random initialisation
    version = shared.publish(field, mapped=1)
    answers = ctx.Queue()
    reader = ctx.Process(target=_reader, args=(shared.buffers, shared.generation, meta, extent, cfg.model, device,
                                               answers))
    reader.start()
    try:
        got_version, sdf, total = answers.get(timeout=120)
    finally:
        reader.join(timeout=30)
    assert got_version == version
    assert sdf == pytest.approx(float(field.sdf(torch.tensor([[0.2, 0.1, 1.0]])).detach()), abs=1e-6)
    assert total == pytest.approx(float(sum(p.detach().double().sum() for p in field.parameters())), rel=1e-6)


# ------------------------------------------------------------------------------------------ the config key

def test_auto_picks_cuda_when_torch_sees_it():
    expected = torch.device("cuda", 0) if torch.cuda.is_available() else torch.device("cpu")
    assert resolve_device("auto") == expected
    assert resolve_device("cpu") == torch.device("cpu")


@pytest.mark.parametrize("spec", ["gpu", "cuda:x", "cpu:1", "CUDA"])
def test_a_misspelt_device_is_refused(spec):
    with pytest.raises(ConfigError, match=r"'run\.device': must be auto, cpu, cuda or cuda:N"):
        load_config("demo", {"run": {"device": spec}})


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA GPU")
@pytest.mark.parametrize("spec", ["cuda", "cuda:0", "cuda:1"])
def test_asking_for_cuda_without_one_stops_with_a_clear_error(spec, capsys, tmp_path):
    with pytest.raises(ConfigError) as e:
        load_config("demo", {"run": {"device": spec}})
    message = str(e.value)
    assert "\n" not in message and "'run.device'" in message and "--device cpu" in message
    assert "CUDA" in message and "Using a GPU" in message
    # The same through the command line: one error line, exit status 2, before any data is read.
    assert main(["run", "--config", "demo", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "out"),
                 "--device", spec]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "invalid value for 'run.device'" in err and not (tmp_path / "out").exists()


def test_a_checkpoint_loads_where_it_is_loaded(room_sequence):
    """A checkpoint made on a GPU machine (run.device: cuda) opens on this one, on the device asked for."""
    from eslam_core.slam import SLAM

    cfg = load_config("demo", {"mapping": {"first_iterations": 2}, "run": {"device": "cpu"}})
    slam = SLAM(cfg, room_sequence.intrinsics)
    slam.step(room_sequence[0])
    state = slam.state_dict()
    state["config"]["run"]["device"] = "cuda:7"  # as written by a machine with eight GPUs
    assert all(v.device.type == "cpu" for v in state["map"]["field"].values())  # loadable without CUDA
    loaded = SLAM.from_state_dict(state, device="cpu")
    assert loaded.cfg.run.device == "cpu" and loaded.map.field.device == torch.device("cpu")
    torch.testing.assert_close(loaded.map.field.geometry_planes.table, slam.map.field.geometry_planes.table)
    assert SLAM.from_state_dict(state).map.device == resolve_device("auto")


def test_cuda_index_beyond_the_gpus_is_refused():
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    problem = device_problem(f"cuda:{count + 3}")
    assert problem is not None and (f"GPU {count + 3}" in problem or "CPU-only" in problem or "no GPU" in problem)


def test_doctor_reports_what_the_installation_runs_on(capsys):
    assert main(["doctor"]) == 0
    out = capsys.readouterr().out
    assert f"torch {torch.__version__}" in out
    assert f"auto picks {resolve_device('auto')}" in out
    assert "plane_lookup" in out and ("compiled" in out or "fallback to plain torch" in out)
    assert "rclpy importable" in out  # the test install has the ROS extra


def test_doctor_says_how_to_install_a_missing_rclpy(capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "rclpy", None)  # an import of it raises ImportError
    assert main(["doctor"]) == 0
    out = capsys.readouterr().out
    assert "rclpy not importable" in out and "pip install -e '.[ros]'" in out
