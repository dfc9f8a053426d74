"""`eslam eval`: evaluate a run directory, or compare two evaluated runs.

    eslam eval RUN_DIR [--gt-mesh PLY] [--data PATH] [--align none|icp] [--points N] [--depth-views N]
                       [--consistency-frames N] [--no-plots]
    eslam eval --compare RUN_A RUN_B [--out compare.md]

Also runnable as `python -m eslam_core.evaluation.cli ...`. Writes RUN_DIR/report.json, RUN_DIR/report.md and
RUN_DIR/plots/*.png, and prints the Markdown report.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Optional, Sequence

from eslam_core.evaluation.report import (
    ALIGN_CHOICES,
    CONSISTENCY_FRAMES,
    RunDirectoryError,
    compare_runs,
    evaluate_run,
    render_markdown,
    write_report_json,
    write_report_markdown,
)

# Bad input raises ValueError subclasses throughout eslam_core (RunDirectoryError, TrajectoryError, MeshError,
# CullingError, the data set loaders' errors); with OSError (unreadable files) they are printed as one line with
# exit status 2 instead of a traceback.
USER_ERRORS = (ValueError, OSError)


def _count(minimum: int):
    """argparse type: an integer >= minimum."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value

    return parse


def add_eval_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the `eslam eval` arguments to `parser` (a sub-command parser or a standalone one)."""
    parser.add_argument("run_dir", nargs="?", type=Path, help="run directory written by `eslam run --out DIR`")
    parser.add_argument("--compare", nargs=2, type=Path, metavar=("RUN_A", "RUN_B"),
                        help="compare two evaluated runs side by side instead of evaluating one")
    parser.add_argument("--out", type=Path, default=Path("compare.md"),
                        help="where --compare writes its Markdown (default: ./compare.md)")
    parser.add_argument("--gt-mesh", type=Path, default=None,
                        help="ground-truth mesh (PLY); default: <scene>_mesh.ply next to the data set, if present")
    parser.add_argument("--data", type=Path, default=None,
                        help="data set location, if it moved since the run (default: the path in summary.json)")
    parser.add_argument("--align", choices=ALIGN_CHOICES, default="none",
                        help="align the reconstruction to the ground-truth mesh before the metrics (default: none)")
    parser.add_argument("--points", type=_count(1), default=450_000,
                        help="surface samples per mesh for accuracy / completion (default: 450000)")
    parser.add_argument("--depth-views", type=_count(0), default=1000,
                        help="random views for depth L1; 0 disables it (default: 1000)")
    parser.add_argument("--consistency-frames", type=_count(0), default=CONSISTENCY_FRAMES,
                        help="frames (evenly spread) of the depth consistency score, which needs the data set but "
                             f"no ground truth; 0 disables it (default: {CONSISTENCY_FRAMES})")
    parser.add_argument("--no-plots", action="store_true", help="do not write PNG plots")
    return parser


def run_eval(args: argparse.Namespace) -> int:
    """Execute `eslam eval` for parsed arguments; returns the process exit status (0 ok, 2 bad input)."""
    try:
        if args.compare:
            if args.run_dir is not None:
                raise RunDirectoryError("give either RUN_DIR or --compare RUN_A RUN_B, not both")
            markdown = compare_runs(args.compare[0], args.compare[1], out_path=args.out)
            print(markdown)
            print(f"(written to {args.out})")
            return 0
        if args.run_dir is None:
            raise RunDirectoryError("missing RUN_DIR: `eslam eval RUN_DIR` or `eslam eval --compare RUN_A RUN_B`")
        run_dir = Path(args.run_dir)
        report = evaluate_run(
            run_dir,
            gt_mesh=args.gt_mesh,
            data=args.data,
            align=args.align,
            n_points=args.points,
            depth_views=args.depth_views,
            plots=not args.no_plots,
            consistency_frames=args.consistency_frames,
        )
        write_report_json(report, run_dir / "report.json")
        write_report_markdown(report, run_dir / "report.md")
        print(render_markdown(report))
        print(f"(written to {run_dir / 'report.json'} and {run_dir / 'report.md'})")
        return 0
    except USER_ERRORS as error:
        print(f"eslam eval: error: {error}", file=sys.stderr)
        return 2


def main(argv: Optional[Sequence[str]] = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    parser = add_eval_arguments(argparse.ArgumentParser(prog="eslam eval", description=__doc__.splitlines()[0]))
    return run_eval(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
