"""Evaluation of ESLAM runs with the NICE-SLAM / ESLAM protocol, headless on a CPU.

- trajectory_error: timestamp association, Umeyama alignment, ATE and RPE (of `eslam_core.trajectory.Trajectory`s,
  read from TUM files by `eslam_core.datasets.tum`);
- reconstruction: surface sampling, accuracy / completion / completion ratio, ICP, mesh checks;
- depth_l1: depth of both meshes rendered from random views inside the scene;
- the depth consistency of a set of poses (frames' depths warped into each other, no ground truth needed) is the
  runtime's own health figure and lives in `eslam_core.mapping.consistency`; re-exported here;
- plots, report, cli: figures, report.json / report.md for a run directory, and `eslam eval`
  (imported on demand: `from eslam_core.evaluation.report import evaluate_run`).
Culling of meshes to the observed surface lives in eslam_core.outputs.culling (mesh extraction uses it too).
"""
from eslam_core.mapping.consistency import (
    ConsistencyResult,
    KeyframeConsistency,
    PairConsistency,
    choose_pairs,
    keyframe_consistency,
    sequence_consistency,
)
from eslam_core.evaluation.depth_l1 import DepthL1Result, depth_l1
from eslam_core.evaluation.reconstruction import (
    MeshError,
    ReconstructionResult,
    check_mesh,
    icp_align,
    load_mesh,
    reconstruction_metrics,
    sample_surface,
)
from eslam_core.datasets.tum import read_tum, write_tum
from eslam_core.evaluation.trajectory_error import associate, ate, AteResult, rpe, RpeResult, umeyama_alignment
from eslam_core.trajectory import Trajectory, TrajectoryError

__all__ = [
    "AteResult",
    "ConsistencyResult",
    "DepthL1Result",
    "KeyframeConsistency",
    "PairConsistency",
    "MeshError",
    "ReconstructionResult",
    "RpeResult",
    "Trajectory",
    "TrajectoryError",
    "associate",
    "ate",
    "check_mesh",
    "choose_pairs",
    "depth_l1",
    "icp_align",
    "keyframe_consistency",
    "load_mesh",
    "reconstruction_metrics",
    "read_tum",
    "rpe",
    "sample_surface",
    "sequence_consistency",
    "umeyama_alignment",
    "write_tum",
]
