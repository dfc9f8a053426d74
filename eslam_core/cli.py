"""The `eslam` command: run, demo, mesh, eval, doctor, and the commands installed packages add (bag)."""
from __future__ import annotations

import argparse
import logging
import sys
from importlib.metadata import entry_points
from pathlib import Path
from typing import Optional, Sequence

import yaml

from eslam_core.camera import Intrinsics
from eslam_core.config import list_presets
from eslam_core.atomic import OutputWriteError

log = logging.getLogger("eslam")


def parse_frames(text: str) -> tuple[int, Optional[int]]:
    """'A:B' (either side optional) -> (start, stop)."""
    try:
        a, _, b = text.partition(":")
        return (int(a) if a else 0, int(b) if b else None)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--frames expects A:B (e.g. 0:100 or 50:), got {text!r}") from None


def parse_overrides(items: Sequence[str]) -> dict:
    """['tracking.iterations=4', ...] -> nested dict, values parsed as YAML."""
    out: dict = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise argparse.ArgumentTypeError(f"--set expects section.key=value, got {item!r}")
        node = out
        parts = key.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = yaml.safe_load(value)
    return out


def _camera_override(cfg) -> Optional[Intrinsics]:
    c = cfg.camera
    if c.fx is None:
        return None
    return Intrinsics(c.width, c.height, c.fx, c.fy, c.cx, c.cy)


def open_configured_dataset(cfg, data: Path, frames: tuple, stride: int):
    from eslam_core.datasets import open_dataset

    ds = open_dataset(data, cfg.dataset.kind, intrinsics=_camera_override(cfg), depth_scale=cfg.camera.depth_scale,
                      register_colour=cfg.dataset.register_colour)
    return ds.subset(frames[0], frames[1], stride)


def cmd_run(args) -> int:
    from eslam_core.config import load_config
    from eslam_core.runner import run_sequence

    if args.localize is not None and (args.resume is not None or args.workers != 1):
        raise ValueError("--localize tracks against a saved map in lock-step: drop --resume and --workers 2")
    if args.catch_up_iterations is not None and args.workers != 2:
        raise ValueError("--catch-up-iterations applies to the pipelined runtime: add --workers 2 (lock-step maps "
                         "every keyframe in full)")
    overrides = parse_overrides(args.set)
    if args.device is not None:  # checked with the rest of the config: a missing GPU is one clear error line
        overrides.setdefault("run", {})["device"] = args.device
    cfg = load_config(args.config, overrides)
    ds = open_configured_dataset(cfg, Path(args.data), args.frames, args.stride)
    s = run_sequence(cfg, ds, Path(args.out), data_label=str(Path(args.data).resolve()),
                     frames=(args.frames[0], args.frames[1], args.stride), resume=args.resume or args.localize,
                     localize=args.localize is not None,
                     progress=not args.quiet, write_mesh=not args.no_mesh, workers=args.workers, policy=args.policy,
                     runtime_options={} if args.catch_up_iterations is None else
                     {"catch_up_iterations": args.catch_up_iterations})
    ate = "n/a (no ground truth)" if s.ate_rmse_cm is None else f"{s.ate_rmse_cm:.2f} cm"
    stopped = f" (stopped by {s.stopped_by}: trajectory and checkpoint so far)" if s.stopped_by else ""
    print(f"{s.n_frames} frames, {s.seconds_per_frame:.2f} s/frame, ATE RMSE {ate}, "
          f"peak memory {s.peak_memory_mb:.0f} MB -> {s.out_dir}{stopped}")
    return 0


def cmd_demo(args) -> int:
    from eslam_core.config import load_config
    from eslam_core.demo import run_demo

    cfg = load_config("demo", parse_overrides(args.set))
    run_demo(cfg, Path(args.out), n_frames=args.frames, size=args.size, cache=args.cache, progress=not args.quiet)
    return 0


def cmd_mesh(args) -> int:
    from eslam_core.outputs.export import load_checkpoint, map_mesh
    from eslam_core.outputs.mesh import save_ply

    slam = load_checkpoint(Path(args.checkpoint))
    out = Path(args.out) if args.out else Path(args.checkpoint).with_name(f"mesh_{args.resolution:g}.ply")
    path = save_ply(map_mesh(slam, args.resolution), out)
    print(f"mesh at {args.resolution:g} m -> {path}")
    return 0


def cmd_eval(args) -> int:
    from eslam_core.evaluation.cli import run_eval

    return run_eval(args)


def cmd_doctor(args) -> int:
    from eslam_core.doctor import report

    print(report())
    return 0


def extension_commands() -> dict:
    """Commands that other installed packages add to `eslam` (entry points of the group `eslam.commands`, each a
    `main(argv) -> int`): the ROS package adds `eslam bag`. The core names no such package: it holds no ROS."""
    return {ep.name: ep for ep in entry_points(group="eslam.commands")}


def cmd_extension(args) -> int:
    try:
        command = args.extension.load()
    except ImportError as e:
        print(f"eslam {args.extension.name} could not load {args.extension.value} ({e}); install what it needs (for "
              f"the ROS tools: pip install -e '.[ros]')", file=sys.stderr)
        return 2
    return command(args.extension_args)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="eslam", description="ESLAM dense RGB-D SLAM (feature planes + TSDF)")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="run SLAM on a data set")
    r.add_argument("--config", required=True, help=f"YAML file or preset name ({', '.join(list_presets())})")
    r.add_argument("--data", required=True, help="data set folder (TUM, ICL-NUIM, Replica, ScanNet, 7-Scenes)")
    r.add_argument("--out", required=True, help="output folder")
    r.add_argument("--frames", type=parse_frames, default=(0, None), help="A:B, frames to run (default all)")
    r.add_argument("--stride", type=int, default=1, help="use every N-th frame")
    r.add_argument("--resume", type=Path, help="continue from a checkpoint.pt: only the frames it has not seen run "
                   "(with --workers 1 or 2)")
    r.add_argument("--localize", type=Path, metavar="CHECKPOINT",
                   help="track and relocalize against the map of a checkpoint.pt, which is left as it is (no "
                        "mapping; run.mode localization)")
    r.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. --set tracking.iterations=4 (repeatable)")
    r.add_argument("--no-mesh", action="store_true", help="skip mesh extraction")
    r.add_argument("--workers", type=int, choices=(1, 2), default=1,
                   help="1: lock-step in this process (default); 2: a tracking and a mapping process in parallel")
    r.add_argument("--policy", choices=("offline", "live"), default="offline",
                   help="offline: every frame in order (default); live: frames fed at the data set's frame rate, "
                        "the tracker skips to the newest when more than runtime.live_backlog (1) frame behind "
                        "(dropped frames are counted)")
    r.add_argument("--catch-up-iterations", type=int, default=None, metavar="N",
                   help="--workers 2: once newer keyframes wait, a mapping step ends after N iterations divided by "
                        "their number, so that the mapper keeps up with the tracker (default: every step runs all "
                        "its iterations)")
    r.add_argument("--device", default=None, metavar="DEVICE",
                   help="where the map, tracking and mapping run: auto (a CUDA GPU when torch sees one), cpu, cuda "
                        "or cuda:N (default: run.device of the config, auto)")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    r.set_defaults(func=cmd_run)

    d = sub.add_parser("demo", help="generate the embedded synthetic room (cached) and run on it")
    d.add_argument("--out", default="runs/demo", help="output folder (default runs/demo)")
    d.add_argument("--frames", type=int, default=60, help="number of frames (default 60)")
    d.add_argument("--size", default="320x240", help="image size WxH (default 320x240)")
    d.add_argument("--cache", type=Path, default=None, help="scene cache folder (default ~/.cache/eslam/scenes)")
    d.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config value")
    d.add_argument("-q", "--quiet", action="store_true")
    d.set_defaults(func=cmd_demo)

    m = sub.add_parser("mesh", help="extract a mesh from a checkpoint at any resolution")
    m.add_argument("checkpoint")
    m.add_argument("--resolution", type=float, default=0.02, help="voxel size in metres (default 0.02)")
    m.add_argument("--out", help="output PLY (default next to the checkpoint)")
    m.set_defaults(func=cmd_mesh)

    try:
        from eslam_core.evaluation.cli import add_eval_arguments
    except ImportError:  # evaluation extras missing: the other commands still work
        add_eval_arguments = None
    if add_eval_arguments is not None:
        e = sub.add_parser("eval", help="evaluate a run: ATE/RPE, reconstruction, depth L1, plots, report")
        add_eval_arguments(e)
        e.set_defaults(func=cmd_eval)

    # `eslam bag write|play|run ...`: everything after the command's name is parsed by the command itself
    # (prefix_chars="\0" keeps argparse from taking `--help` or `--rate` for options of its own).
    for name, extension in sorted(extension_commands().items()):
        x = sub.add_parser(name, help=f"from {extension.module} (`eslam {name} --help` lists what it does)",
                           add_help=False, prefix_chars="\0")
        x.add_argument("extension_args", nargs=argparse.REMAINDER)
        x.set_defaults(func=cmd_extension, extension=extension)

    doc = sub.add_parser("doctor", help="what this installation runs on: torch, CUDA, the device auto picks, the "
                                        "native kernels, the ROS 2 wheels")
    doc.set_defaults(func=cmd_doctor)
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except RuntimeError as e:
        from eslam_core.runtime import RuntimeCrashed

        if not isinstance(e, RuntimeCrashed):
            raise
        # The worker's traceback is already in the log (stderr), written when the crash was detected.
        print(f"eslam: error: {e.summary}; the run was stopped", file=sys.stderr)
        return 1
    except OutputWriteError as e:
        # An output that could not be written (a full disk, a read-only folder): one line per file; the others
        # were written.
        for line in str(e).splitlines():
            print(f"eslam: error: {line}", file=sys.stderr)
        return 1
    except (ValueError, FileNotFoundError) as e:
        # Every input problem is raised as a ValueError subclass whose message names the problem and the fix.
        print(f"eslam: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
