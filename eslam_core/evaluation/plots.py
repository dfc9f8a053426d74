"""Evaluation figures, written as PNG files (matplotlib Agg backend: no display needed).

Each function draws one figure, writes it to `path` (creating the folder) and returns the path.
Figures are built on `matplotlib.figure.Figure` directly, not pyplot, so nothing accumulates in global state when
many runs are evaluated in one process.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence, Union

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

PathLike = Union[str, Path]

_GT_STYLE = dict(color="tab:green", linewidth=1.5, label="ground truth")
_EST_STYLE = dict(color="tab:red", linewidth=1.0, label="estimate (aligned)")


def _save(figure: Figure, path: PathLike) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110, bbox_inches="tight")
    return path


def plot_trajectory(
    gt_positions: np.ndarray, est_positions: np.ndarray, path: PathLike, title: str = "Camera trajectory"
) -> Path:
    """Top view (world x-y) and side view (world x-z) of the ground-truth and aligned estimated camera paths."""
    gt_positions = np.asarray(gt_positions)
    est_positions = np.asarray(est_positions)
    figure = Figure(figsize=(11, 5))
    for panel, (axis_b, label_b) in enumerate([(1, "y"), (2, "z")]):
        ax = figure.add_subplot(1, 2, panel + 1)
        ax.plot(gt_positions[:, 0], gt_positions[:, axis_b], **_GT_STYLE)
        ax.plot(est_positions[:, 0], est_positions[:, axis_b], **_EST_STYLE)
        ax.plot(*gt_positions[0, [0, axis_b]], "o", color="black", markersize=4, label="start")
        ax.set_xlabel("x [m]")
        ax.set_ylabel(f"{label_b} [m]")
        ax.set_title("top view (x-y)" if label_b == "y" else "side view (x-z)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    figure.suptitle(title)
    return _save(figure, path)


def plot_position_error(timestamps: np.ndarray, errors: np.ndarray, path: PathLike,
                        sigma: Optional[np.ndarray] = None) -> Path:
    """Position error (cm) of each matched pose over time, with its RMSE as a reference line and, where given, the
    predicted standard deviation of each pose (the tracker's covariance)."""
    timestamps = np.asarray(timestamps, dtype=np.float64)
    errors_cm = 100.0 * np.asarray(errors, dtype=np.float64)
    figure = Figure(figsize=(9, 3.5))
    ax = figure.add_subplot(1, 1, 1)
    ax.plot(timestamps - timestamps[0], errors_cm, color="tab:red", linewidth=1.0, label="position error")
    if sigma is not None:
        ax.plot(timestamps - timestamps[0], 100.0 * np.asarray(sigma, dtype=np.float64), color="tab:blue",
                linewidth=1.0, label="predicted sigma")
    rmse = float(np.sqrt(np.mean(errors_cm**2)))
    ax.axhline(rmse, color="black", linestyle="--", linewidth=0.8, label=f"RMSE {rmse:.2f} cm")
    ax.set_xlabel("time since first frame [s or frames]")
    ax.set_ylabel("ATE [cm]")
    ax.set_ylim(bottom=0)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    return _save(figure, path)


def plot_depth_errors(views: Sequence[tuple[np.ndarray, np.ndarray]], path: PathLike) -> Path:
    """One row per view: ground-truth depth, reconstructed depth (same colour scale), |error| in cm with colour bar.

    `views` holds (gt_depth, rec_depth) pairs in metres, 0 = no surface.
    """
    if not views:
        raise ValueError("plot_depth_errors needs at least one (gt_depth, rec_depth) pair")
    figure = Figure(figsize=(12, 3.2 * len(views)))
    for row, (gt_depth, rec_depth) in enumerate(views):
        gt_depth = np.asarray(gt_depth, dtype=np.float64)
        rec_depth = np.asarray(rec_depth, dtype=np.float64)
        both = (gt_depth > 0) & (rec_depth > 0)
        error_cm = np.where(both, 100.0 * np.abs(gt_depth - rec_depth), np.nan)
        far = max(float(gt_depth.max()), float(rec_depth.max()), 1e-3)
        # The 99th percentile sets the colour scale: a few silhouette pixels with metre-size errors would
        # otherwise turn the whole error image black.
        worst = float(np.nanpercentile(error_cm, 99)) if both.any() else 1.0
        for column, (image, title, cmap, vmax) in enumerate(
            [
                (np.where(gt_depth > 0, gt_depth, np.nan), "ground-truth depth [m]", "viridis", far),
                (np.where(rec_depth > 0, rec_depth, np.nan), "reconstructed depth [m]", "viridis", far),
                (error_cm, "|error| [cm] (white: no overlap)", "magma", max(worst, 1e-3)),
            ]
        ):
            ax = figure.add_subplot(len(views), 3, 3 * row + column + 1)
            shown = ax.imshow(image, cmap=cmap, vmin=0, vmax=vmax)
            ax.set_title(f"view {row}: {title}", fontsize=9)
            ax.axis("off")
            figure.colorbar(shown, ax=ax, fraction=0.035, pad=0.02, extend="max" if column == 2 else "neither")
    return _save(figure, path)


def plot_consistency(estimate_pairs: Sequence, reference_pairs: Optional[Sequence], path: PathLike,
                     agree_cm: float = 3.0) -> Path:
    """Depth consistency over the sequence: each pair's median |residual| (mm) and agreement (%), placed at its
    later frame; near pairs as lines, far pairs (revisits) as dots; estimated poses red, reference poses green.

    The pairs are `consistency.PairConsistency` records (first, second, kind, median_mm, agree_fraction).
    """
    figure = Figure(figsize=(10, 6))
    panels = (("median_mm", "median |depth residual| [mm]"), ("agree_fraction", f"agreeing within {agree_cm:g} cm [%]"))
    sets = [("estimate", estimate_pairs, "tab:red")]
    if reference_pairs:
        sets.append(("reference", reference_pairs, "tab:green"))
    for row, (field, label) in enumerate(panels):
        ax = figure.add_subplot(2, 1, row + 1)
        for name, pairs, colour in sets:
            scale = 100.0 if field == "agree_fraction" else 1.0
            near = sorted((p.second, scale * getattr(p, field)) for p in pairs if p.kind != "far")
            far = [(p.second, scale * getattr(p, field)) for p in pairs if p.kind == "far"]
            if near:
                ax.plot(*zip(*near), color=colour, linewidth=1.0, label=f"{name}, near pairs")
            if far:
                ax.plot(*zip(*far), "o", color=colour, markersize=3, alpha=0.6, label=f"{name}, far pairs")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
        if row == 0:
            ax.set_ylim(bottom=0)
            ax.legend(loc="upper left", fontsize=8)
    ax.set_xlabel("frame (the later frame of each pair)")
    figure.suptitle("Depth consistency: frames' depths warped into each other with the poses")
    return _save(figure, path)
