"""The map checked against itself (tracking/map_check.py): a keyframe placed by an older one's features either
agrees with its tracked pose, disagrees by a slide, or lies too far away to be the same place."""
import numpy as np

from eslam_core.config import RelocalizationConfig
from eslam_core.geometry import rotvec_to_matrix
from eslam_core.tracking.map_check import compared
from eslam_core.tracking.relocalization import KeyframeDatabase, KeyframeEntry


def _pose(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = rotvec_to_matrix(np.radians([0.0, 0.0, yaw_deg]))
    pose[0, 3] = x
    return pose


def test_a_placement_agrees_disagrees_by_a_slide_or_is_another_place():
    cfg = RelocalizationConfig()  # map_disagree_m 0.2, map_disagree_deg 10, max_jump_m 1
    tracked = _pose(2.0)
    near = compared(30, 5, _pose(2.05), tracked, cfg)
    assert near is not None and not near.disagrees and abs(near.metres - 0.05) < 1e-9
    slide = compared(30, 5, _pose(2.5), tracked, cfg)  # a slide mapped earlier (the two planes': about 0.5 m)
    assert slide is not None and slide.disagrees and abs(slide.metres - 0.5) < 1e-9 and slide.by == 5
    turned = compared(30, 5, _pose(2.0, yaw_deg=30), tracked, cfg)
    assert turned is not None and turned.disagrees and abs(turned.degrees - 30) < 1e-6
    # The same furniture in another room, 4 m away and turned round: no check at all, not a disagreement.
    assert compared(30, 5, _pose(6.0, yaw_deg=180), tracked, cfg) is None


def _entry(number: int, pose: np.ndarray) -> KeyframeEntry:
    none = np.zeros((0, 2), np.float32)
    return KeyframeEntry(number, none, np.zeros((0, 32), np.uint8), np.zeros((0, 3)), np.zeros(1200, np.float32),
                         pose)


def test_the_keyframes_near_a_return_are_checked_nearest_first_if_they_look_the_same_way():
    """Where the scene repeats itself, appearance ranks look-alike places first: the map check also verifies the
    older keyframes where the camera is believed to be (within max_jump_m, looking within 45 degrees of its way)."""
    def looking(x: float, turn_deg: float = 0.0) -> np.ndarray:  # the optical axis (z) turned about y
        pose = _pose(x)
        pose[:3, :3] = rotvec_to_matrix(np.radians([0.0, turn_deg, 0.0]))
        return pose

    db = KeyframeDatabase(RelocalizationConfig())  # candidates 3, max_jump_m 1
    poses = {0: looking(0.3), 1: looking(0.1), 2: looking(0.6, 30), 3: looking(0.0, 180), 4: looking(1.5),
             5: looking(-0.15), 6: looking(-0.7, -40)}
    for number, pose in poses.items():
        db.insert(_entry(number, pose))
    returned = looking(0.05)
    assert db.nearby(returned, list(poses)) == [1, 5, 0]  # the three nearest that look its way
    assert db.nearby(returned, [2, 3, 4, 6]) == [2, 6]  # turned round (3) or 1.45 m away (4): not the same view
    assert db.nearby(returned, []) == []
