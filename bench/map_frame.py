"""How the map frame's orientation against the scene changes accuracy (eslam_core/mapping/map_frame.py).

    python bench/map_frame.py --data ../shared/data/icl_office_kt0 --kind icl --frames 1:300 --modes turned,squared
    python bench/map_frame.py --data ../shared/data/7scenes_redkitchen_0_399 --kind 7scenes

The same frames through the two-process runtime (`--workers 2`, offline policy, no mesh), once per start:
- ground-truth: the first frame at its reference pose (how `eslam run` scores a data set; the data set's frame);
- squared: as a live camera starts (no reference pose): the first camera's frame squared with the scene;
- camera: as a live camera starts, `scene.align_axes: false`: the first camera's frame as it is;
- turned: the first frame at its reference position, its orientation turned by `--turn` degrees about a random
  axis (one run per `--seeds`): a data set whose world frame is squared with the room, seen by a camera held at
  another angle.
Only the first frame's pose is changed, and only its rotation where it is kept: ATE scores positions, so the score
is unaffected. Prints ATE RMSE per run; writes JSON.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from eslam_core.cli import parse_frames  # noqa: E402
from eslam_core.config import load_config  # noqa: E402
from eslam_core.datasets import open_dataset  # noqa: E402
from eslam_core.geometry import rotvec_to_matrix  # noqa: E402
from eslam_core.runner import run_sequence  # noqa: E402

MODES = ("ground-truth", "squared", "camera", "turned")


class FirstPose:
    """A data set whose first frame carries another pose (None: no reference pose); every other frame as read."""

    def __init__(self, dataset, pose):
        self.dataset, self.pose = dataset, pose

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, i: int):
        frame = self.dataset[i]
        return replace(frame, pose=self.pose) if i == 0 else frame

    def __getattr__(self, name: str):
        return getattr(self.dataset, name)


def first_poses(reference, modes: list[str], turn_deg: float, seeds: int):
    """(label, first pose, align_axes) per run."""
    for mode in modes:
        if mode == "ground-truth":
            yield mode, reference, True
        elif mode in ("squared", "camera"):
            yield mode, None, mode == "squared"
        else:
            if reference is None:
                raise SystemExit("turned: the first frame needs a reference pose (ICL-NUIM: --frames 1:300)")
            for seed in range(seeds):
                axis = np.random.default_rng(seed).normal(size=3)
                pose = reference.copy()
                pose[:3, :3] = reference[:3, :3] @ rotvec_to_matrix(np.radians(turn_deg) * axis / np.linalg.norm(axis))
                yield f"turned {turn_deg:g} deg (seed {seed})", pose, True


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True)
    ap.add_argument("--kind", default="auto")
    ap.add_argument("--frames", default=None, help="A:B (default all)")
    ap.add_argument("--config", default="live")
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--turn", type=float, default=30.0, help="degrees (turned)")
    ap.add_argument("--seeds", type=int, default=2, help="turned runs, one random axis each")
    ap.add_argument("--out", type=Path, default=Path("map_frame.json"))
    args = ap.parse_args()
    modes = args.modes.split(",")
    if unknown := set(modes) - set(MODES):
        raise SystemExit(f"unknown modes {sorted(unknown)}; choose from {', '.join(MODES)}")
    logging.basicConfig(level=logging.WARNING)

    dataset = open_dataset(args.data, args.kind)
    if args.frames:
        dataset = dataset.subset(*parse_frames(args.frames))
    reference = dataset[0].pose
    rows = []
    for label, pose, align in first_poses(reference, modes, args.turn, args.seeds):
        cfg = load_config(args.config, {"dataset": {"kind": dataset.kind}, "scene": {"align_axes": align}})
        with tempfile.TemporaryDirectory() as out:
            summary = run_sequence(cfg, FirstPose(dataset, pose), Path(out), data_label=args.data, progress=False,
                                   write_mesh=False, workers=2)
        rows.append({"start": label, "ate_rmse_cm": summary.ate_rmse_cm,
                     "seconds_per_frame": summary.seconds_per_frame})
        print(f"{label:<28} ATE {summary.ate_rmse_cm:.2f} cm  ({summary.seconds_per_frame:.3f} s/frame)", flush=True)
    args.out.write_text(json.dumps({"data": args.data, "frames": args.frames, "config": args.config, "runs": rows},
                                   indent=1))
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
