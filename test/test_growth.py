"""A map without edges and a keyframe store with a budget: the map grows where the camera goes, features stay
where they are in the world, the store stays under its budget, and SLAM still tracks."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from eslam_core.camera import Intrinsics
from eslam_core.config import ModelConfig, load_config
from eslam_core.datasets.tum import read_tum
from eslam_core.evaluation.trajectory_error import still_camera_ate
from eslam_core.mapping.extent import grown_extent
from eslam_core.mapping.keyframes import REDUCED_STRIDE, Keyframe, KeyframeStore
from eslam_core.mapping.observed import ObservedSpace
from eslam_core.representation.field import SceneField
from eslam_core.runner import run_sequence

from eslam_core.demo import mesh_scores

COARSE = 0.24


def test_grown_field_keeps_its_features_where_they_are():
    bound = np.array([[-0.48, -0.24, 0.0], [0.48, 0.48, 0.72]])
    field = SceneField(bound, ModelConfig(coarse_resolution=COARSE))
    with torch.no_grad():
        for p in field.plane_parameters():
            p.normal_()
    points = torch.rand(500, 3, dtype=torch.float32) * torch.tensor(bound[1] - bound[0]).float() + \
        torch.tensor(bound[0]).float()
    before = field(points)
    bigger = np.array([bound[0] - [0.48, 0.0, 0.24], bound[1] + [0.24, 0.72, 0.0]])
    grown = field.grown(bigger)
    after = grown(points)
    assert torch.allclose(before[0], after[0], atol=1e-5) and torch.allclose(before[1], after[1], atol=1e-5)
    assert grown.parameter_count() > field.parameter_count()
    # the new cells start as new cells do: small random features, not copies of the border
    new_rows = grown.geometry_planes.plane_rows(0, 0)[:, :2]  # the two new columns along x, coarse xy plane
    assert 0.001 < float(new_rows.std()) < 0.05


def test_extent_grows_by_whole_cells_up_to_the_cap():
    extent = np.array([[0.0, 0.0, 0.0], [0.96, 0.96, 0.96]])
    points = torch.tensor([[1.1, 0.5, 0.5], [-0.3, 0.5, 0.5]])
    new, left_out = grown_extent(extent, points, COARSE, 0.1, max_extent=10.0)
    assert left_out == 0
    cells = (new - extent) / COARSE
    assert np.allclose(cells, np.round(cells)) and new[1, 0] >= 1.2 and new[0, 0] <= -0.4
    assert np.array_equal(new[:, 1:], extent[:, 1:])  # only the sides the points leave
    stray = torch.tensor([[50.0, 0.5, 0.5]])  # a stray depth reading far away: growth stops at the cap
    capped, left_out = grown_extent(extent, stray, COARSE, 0.1, max_extent=3.0)
    assert capped[1, 0] - capped[0, 0] <= 3.0 + 1e-9 and left_out == 1


def test_observed_space_grows_without_moving():
    space = ObservedSpace(np.array([[0.0, 0.0, 0.0], [0.6, 0.6, 0.6]]), 0.06)
    p = torch.tensor([[0.31, 0.2, 0.5]])
    space.add(p)
    grown = space.grown(np.array([[-0.48, -0.24, 0.0], [1.2, 0.6, 0.9]]))
    assert grown.contains(p).item() and not grown.contains(torch.tensor([[0.9, 0.2, 0.5]])).item()
    assert int(grown.seen.sum()) == 1


def _keyframe(number: int, h: int = 60, w: int = 80) -> Keyframe:
    g = torch.Generator().manual_seed(number)
    pose = torch.eye(4)
    pose[0, 3] = 0.05 * number
    return Keyframe.from_tensors(number, 0.1 * number, torch.rand(h, w, 3, generator=g),
                                 1.0 + torch.rand(h, w, generator=g), torch.ones(h, w, dtype=torch.bool), pose, number)


def test_keyframe_store_stays_within_its_budget():
    intr = Intrinsics(80, 60, 70.0, 70.0, 39.5, 29.5)
    full = _keyframe(0).nbytes()
    store = KeyframeStore(budget_bytes=6 * full, keep_full=4)
    for i in range(60):
        store.append(_keyframe(i), intr, torch.tensor([[0.05 * i, 0.0, 2.0]]))
        assert store.nbytes() <= 6 * full
    assert all(kf.stride == 1 for kf in store.items[-4:])  # the newest keep every pixel
    assert store.reduced > 0 and store.dropped > 0 and len(store) > 6
    numbers = [kf.number for kf in store]
    assert numbers == sorted(numbers) and numbers[-1] == 59 and store.made == 60


def test_a_camera_standing_still_does_not_fill_the_store():
    """Later keyframes of the same view are dropped once they are not among the newest: the store grows with the
    explored space, not with time, and keeps the first keyframe of the view (the map's anchor there)."""
    intr = Intrinsics(80, 60, 70.0, 70.0, 39.5, 29.5)
    store = KeyframeStore(budget_bytes=0, keep_full=4)
    surface = torch.stack(torch.meshgrid(torch.linspace(-0.2, 0.2, 10), torch.linspace(-0.1, 0.1, 10),
                                         indexing="ij"), -1).reshape(-1, 2)
    points = torch.cat([surface, torch.full((100, 1), 2.0)], 1)
    for i in range(40):
        kf = _keyframe(i)
        kf.pose = torch.eye(4)
        store.append(kf, intr, points)
    assert len(store) <= 5 and store.dropped >= 35 and store[-1].number == 39 and store[0].number == 0
    gone = store.take_dropped()  # what the relocalization index forgets
    assert len(gone) == store.dropped and not set(gone) & {kf.number for kf in store} and not store.take_dropped()


def test_reduced_keyframe_reads_the_frames_pixels():
    kf = _keyframe(3)
    small = kf.reduced()
    idx = torch.arange(small.usable.numel())
    frame_idx = small.frame_pixels(idx, 80)
    assert torch.equal(small.depths(idx), kf.depths(frame_idx)) and torch.equal(small.colors(idx), kf.colors(frame_idx))
    assert small.nbytes() < kf.nbytes() / (REDUCED_STRIDE**2 - 2)
    assert small.frame_depth_image(60, 80).shape == (60, 80)


# ------------------------------------------------------------------------------------------- SLAM in the long room

ROOM = [[-4.0, -1.5, 0.0], [4.0, 1.5, 2.6]]


def _run(long_room, out, workers: int = 1, **scene):
    cfg = load_config("fast", {"scene": {"bound_margin": 0.3, **scene}})
    summary = run_sequence(cfg, long_room, out, progress=False, workers=workers)
    return summary, json.loads((out / "summary.json").read_text())


@pytest.fixture(scope="module")
def grown_and_bounded(long_room, tmp_path_factory):
    grown = _run(long_room, tmp_path_factory.mktemp("grown"))
    bounded = _run(long_room, tmp_path_factory.mktemp("bounded"),
                   bound=[[a - 0.1 for a in ROOM[0]], [b + 0.1 for b in ROOM[1]]])
    return grown, bounded


def test_map_grows_with_the_camera_and_drops_no_depth(grown_and_bounded, long_room):
    (summary, s), _ = grown_and_bounded
    first = long_room[0]
    start_x = first.pose[0, 3]
    assert s["map_growths"] >= 1 and s["points_outside_bound"] == 0
    assert s["bound"][1][0] > start_x + 3.0  # the map reached far beyond the first view along the walk
    assert 2.0 < 0.5 * 100 * still_camera_ate(np.stack(long_room.gt_poses())[:, :3, 3])
    assert summary.ate_rmse_cm < 2.0


def test_grown_map_is_as_complete_as_one_with_a_hand_set_bound(grown_and_bounded, long_room):
    (grown, _), (bounded, _) = grown_and_bounded
    truth = long_room.root / "mesh.ply"
    a = mesh_scores(grown.mesh_path, truth, long_room, 0.06, n_points=60_000)
    b = mesh_scores(bounded.mesh_path, truth, long_room, 0.06, n_points=60_000)
    assert a.completion_ratio >= b.completion_ratio - 0.01 and a.completion_ratio > 0.5


def test_growth_in_the_pipelined_runtime(long_room, tmp_path):
    """The mapper grows the map while the tracker works on the old one: a new shared-map generation, read whole.
    The camera walks 2.5 cm a frame into new space, and the tracker may be a few keyframes ahead of the map: a view
    that has left the mapped space waits for the map to catch up (it was lost when the mapper was behind)."""
    summary, s = _run(long_room, tmp_path, workers=2)
    assert 3.0 < 0.5 * 100 * still_camera_ate(np.stack(long_room.gt_poses())[:, :3, 3])
    assert s["runtime"]["workers_figures"]["map_bytes"] > 0
    assert s["points_outside_bound"] == 0 and summary.ate_rmse_cm < 3.0
    assert s["map_growths"] >= 1  # counted by the mapper, carried into the final state with the map
    est = read_tum(tmp_path / "trajectory.txt")
    assert len(est.timestamps) == len(long_room) and np.isfinite(est.poses).all()


def test_slam_under_keyframe_budget_pressure(room_sequence, tmp_path):
    """A store that holds only a few full keyframes reduces and drops the old ones, and SLAM still tracks."""
    full_mb = 160 * 120 * 6 / 2**20
    budget = 10 * full_mb  # 15 keyframes (one every 2 frames), the newest 8 kept whole
    cfg = load_config("demo", {"mapping": {"keyframe_budget_mb": budget, "first_iterations": 100, "every": 2}})
    summary = run_sequence(cfg, room_sequence, tmp_path, progress=False, write_mesh=False)
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["keyframe_bytes"] <= budget * 2**20 and s["keyframes_reduced"] + s["keyframes_dropped"] > 0
    assert 2.0 < 0.5 * 100 * still_camera_ate(np.stack(room_sequence.gt_poses())[:, :3, 3])
    assert summary.ate_rmse_cm < 2.0
