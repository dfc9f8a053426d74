"""Never silently wrong: views that leave the pose free (a wall, a ceiling meeting a wall, a corridor), generated
with faint texture and a Kinect-like sensor (datasets/degenerate.py).

Before the degeneracy-aware tracker, `fast` lock-step on the two-plane sequence slid 97 cm with every frame at
quality 1.0 and the slide's keyframes mapped. Now a frame more than 2 cm off must say so (degraded or lost), none of
those frames may be mapped, and once the camera is back on the constrained view the error is under 1 cm again.
"""
import numpy as np
import pytest
import torch

from eslam_core.config import load_config
from eslam_core.datasets import open_dataset
from eslam_core.datasets.degenerate import generate_degenerate_scene, stretch_of
from eslam_core.datasets.synthetic import generate_scene
from eslam_core.frames import prepare_frame
from eslam_core.runtime import make_runtime
from eslam_core.slam import SLAM
from eslam_core.tracking.frontend import make_tracker

FLAG_ABOVE_M = 0.02  # a pose further off than this must be flagged
BACK_UNDER_M = 0.01  # ... and after the stretch the error must be back under this
_SCENES: dict = {}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """The generated sequence of a view (160 x 120, 230 frames), made once per module."""
    def get(view: str):
        if view not in _SCENES:
            _SCENES[view] = generate_degenerate_scene(tmp_path_factory.mktemp(view) / "seq", view)
        return _SCENES[view]
    return get


@pytest.mark.parametrize("view, preset, workers", [
    ("two_planes", "fast", 1), ("plane", "live", 1), ("two_planes", "live", 2), ("plane", "fast", 2)])
def test_a_view_that_leaves_the_pose_free_is_flagged_never_mapped_and_left_again(scene, view, preset, workers):
    path = scene(view)
    data = open_dataset(path, "tum")
    stretch, _ = stretch_of(path)
    updates = []
    rt = make_runtime(load_config(preset), data.intrinsics, workers=workers, policy="offline", threads=1)
    with rt:
        for frame in data:
            rt.submit(frame)
            updates += rt.poll()
    updates += rt.poll()
    assert [u.index for u in updates] == list(range(len(data)))
    truth = np.stack(data.gt_poses())[:, :3, 3]
    error = np.linalg.norm(np.stack([u.pose[:3, 3] for u in updates]) - truth, axis=1)
    flagged = np.array([u.degraded or u.lost for u in updates])
    keyframe = np.array([u.keyframe for u in updates])
    off = error > FLAG_ABOVE_M
    assert not (off & ~flagged).any(), f"unflagged frames {np.flatnonzero(off & ~flagged)} are " \
        f"{100 * error[off & ~flagged].max():.1f} cm off"
    assert not (off & keyframe).any(), f"frames {np.flatnonzero(off & keyframe)} were mapped"
    assert flagged[stretch.start - 20:stretch.stop].any()  # the view was seen for what it is
    after = slice(len(data) - 10, len(data))
    assert error[after].max() < BACK_UNDER_M, f"after the stretch still {100 * error[after].max():.1f} cm off"
    assert np.linalg.norm(truth[after] - truth[0], axis=1).min() > 10 * BACK_UNDER_M  # a still camera fails


@pytest.mark.parametrize("view", ["two_planes", "corridor"])
def test_the_covariance_is_widest_along_the_free_direction(scene, view):
    """The map made from the true poses; each frame of the stretch tracked from its true pose: the covariance's
    largest position axis lies along the direction the view leaves free."""
    path = scene(view)
    data = open_dataset(path, "tum")
    stretch, free = stretch_of(path)
    slam = SLAM(load_config("fast", {"tracking": {"mode": "external"}}), data.intrinsics)
    for frame in data:
        frame.odom_pose = frame.pose
        slam.step(frame)
    cfg = load_config("fast")
    tracker = make_tracker(cfg, slam.dirs_cam, slam.intr)
    cosines = []
    for i in range(stretch.start, stretch.stop, 5):
        pf = prepare_frame(data[i], slam.input_intrinsics, cfg.camera)
        result = tracker.track(slam.map.field, pf, torch.from_numpy(data[i].pose).float(), slam.map.extent,
                               slam.map.observed, slam.map.newest_keyframe(), slam.map.version)
        cosines.append(abs(result.covariance.weak_direction @ free))
    assert np.degrees(np.arccos(min(np.median(cosines), 1.0))) < 25.0


def test_the_covariance_is_the_size_of_the_errors_on_the_room(tmp_path):
    """Calibration: over 120 frames of the room (4 s, 1 m walked), each frame's position error against the truth is
    of the size of its predicted standard deviation (sqrt of the position covariance's trace): the median ratio was
    0.36 here, 0.40 on ICL office kt0 and 2.57 on 7-Scenes RedKitchen (README)."""
    room = open_dataset(generate_scene(tmp_path / "room", n_frames=120, width=160, height=120, seed=3), "tum")
    slam = SLAM(load_config("fast"), room.intrinsics)
    ratios = []
    for frame in room:
        step = slam.step(frame)
        if step.covariance is not None:
            error = np.linalg.norm(step.pose[:3, 3] - frame.pose[:3, 3])
            ratios.append(error / np.sqrt(np.trace(step.covariance[:3, :3])))
    assert len(ratios) == len(room) - 1
    assert 0.3 < np.median(ratios) < 3.0, f"median error / sigma {np.median(ratios):.2f}"
