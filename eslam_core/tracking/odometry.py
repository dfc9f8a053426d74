"""Frame-to-frame RGB-D odometry: the tracker's starting pose (not part of the paper's method).

The map trackers refine a prediction locally: the SDF residuals saturate at the truncation T (6 cm), and a rotation
of a few degrees moves far points by more than that, so a prediction that is 5 cm / 5 degrees off lands in a wrong
minimum (measured on the synthetic room at the `live` settings: 6 of 8 such starts ended 1.5-7.4 cm off). The
constant-velocity prediction is that far off whenever the motion changes: a hand-held camera that jerks, a frame
missing from the stream (ICL frame 274 -> 275, 1.3 cm and 1.65 degrees in one gap), frames a live tracker skipped,
the turn at the end of a pass.

Dense RGB-D odometry (OpenCV's `Odometry`: photometric and point-to-plane ICP residuals over an image pyramid)
between the last well-tracked frame and the new one, on small images, measures that motion directly: on ICL and
7-Scenes pairs 1 to 12 frames apart (up to 4.3 cm and 7.3 degrees) it was within 0.1-0.4 cm and 0.4 degrees of the
reference poses at 160 x 120 pixels, in about 5 ms per frame on one core. OpenCV refuses motions beyond its limits
(15 cm, 15 degrees) and says when it failed; then the constant-velocity prediction stands.
"""
from __future__ import annotations

from typing import Optional, Sequence

import cv2
import numpy as np
import torch

from eslam_core.camera import Intrinsics


def small_images(rgb: torch.Tensor, depth: torch.Tensor, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) colour in [0, 1] and (H, W) depth -> grey uint8 and depth float32 at 1/factor of the size. Depth
    takes the nearest pixel: an average across a depth edge is a surface that is not there."""
    rgb_np, depth_np = rgb.contiguous().numpy(), depth.contiguous().numpy()
    h, w = depth_np.shape[0] // factor, depth_np.shape[1] // factor
    grey = cv2.cvtColor(rgb_np, cv2.COLOR_RGB2GRAY)
    if factor > 1:
        grey = cv2.resize(grey, (w, h), interpolation=cv2.INTER_AREA)
        depth_np = np.ascontiguousarray(depth_np[factor // 2::factor, factor // 2::factor][:h, :w])
    return cv2.convertScaleAbs(grey, alpha=255.0), depth_np.astype(np.float32, copy=False)


class RGBDOdometry:
    """The motion of the camera between the last frame it was given as a reference and a new one."""

    def __init__(self, intr: Intrinsics, width: int, max_depth: float = 0.0,
                 iterations: Optional[Sequence[int]] = None):
        if not hasattr(cv2, "Odometry"):
            raise RuntimeError(f"odometry.width needs OpenCV >= 5.1 (cv2.Odometry), this is OpenCV "
                               f"{cv2.__version__}: pip install 'opencv-python-headless>=5.1', or set "
                               f"odometry.width: 0")
        self.factor = max(1, round(intr.width / width))
        small = intr.scaled(1.0 / self.factor)
        K = np.array([[small.fx, 0, small.cx], [0, small.fy, small.cy], [0, 0, 1]], np.float32)
        settings = cv2.OdometrySettings()
        settings.setCameraMatrix(K)
        if max_depth > 0:
            settings.setMaxDepth(float(max_depth))
        if iterations is not None:  # per pyramid level, finest first (None: OpenCV's own)
            # OpenCV 5.1's binding reads the count of level i from row i, column 0 of a matrix with one column per
            # level (a vector of ints does not pass through the Python binding).
            counts = np.asarray(iterations, np.int32)
            settings.setIterCounts(np.repeat(counts[:, None], len(counts), axis=1))
        self.odometry = cv2.Odometry(cv2.OdometryType_RGB_DEPTH, settings, cv2.OdometryAlgoType_COMMON)
        self.reference: Optional[cv2.OdometryFrame] = None
        self.reference_key: object = None

    def frame(self, rgb: torch.Tensor, depth: torch.Tensor) -> cv2.OdometryFrame:
        """A frame prepared (pyramids, normals) for either side of a motion."""
        grey, small_depth = small_images(rgb, depth, self.factor)
        prepared = cv2.OdometryFrame(small_depth, grey)  # (OpenCV 5 takes the depth first)
        self.odometry.prepareFrame(prepared)
        return prepared

    def set_reference(self, key: object, frame: cv2.OdometryFrame) -> None:
        """The frame that later motions start from; `key` says which one it is (a trajectory position)."""
        self.reference, self.reference_key = frame, key

    def motion(self, frame: cv2.OdometryFrame) -> Optional[np.ndarray]:
        """T_ref^-1 T_frame, the new camera's pose in the reference camera (4 x 4), or None where the odometry
        failed."""
        if self.reference is None:
            return None
        ok, Rt = self.odometry.compute(self.reference, frame)  # Rt maps reference camera points into the new one's
        if not ok or not np.isfinite(Rt).all():
            return None
        return np.linalg.inv(Rt.astype(np.float64))
