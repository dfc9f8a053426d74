"""What a tracker returns for a frame: the pose and the evidence for its quality (quality.py). Both trackers
(render_tracker.py, sdf_tracker.py) return it, the front end (frontend.py) reads it."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from eslam_core.tracking.information import PoseCovariance


@dataclass
class TrackingResult:
    pose: torch.Tensor  # (4, 4) camera-to-world
    loss: float  # best loss over the iterations
    rays: int  # rays per iteration after dropping those without depth
    # The evidence for the tracking quality (quality.py), NaN where not measured: pixels with depth inside the
    # border / pixels inside the border; scored points within the truncation of the mapped surface at the
    # returned pose; scored points in observed space.
    depth_fraction: float = float("nan")
    inlier_fraction: float = float("nan")
    observed_fraction: float = float("nan")
    # Depth points inside the border that the map can score at the starting pose (in its extent and, for the SDF
    # tracker, in observed space) / depth points inside the border: low when the view has left the mapped space.
    mapped_fraction: float = float("nan")
    covariance: PoseCovariance | None = None  # of the pose (information.py); None where not measured

    def in_world(self, anchor: np.ndarray) -> "TrackingResult":
        """The result of tracking in a submap's frame (its anchor: the frame's world pose), in the world's."""
        A = torch.from_numpy(np.asarray(anchor, dtype=np.float64)).to(self.pose.dtype)
        covariance = None if self.covariance is None else self.covariance.rotated(anchor[:3, :3])
        return replace(self, pose=A @ self.pose, covariance=covariance)
