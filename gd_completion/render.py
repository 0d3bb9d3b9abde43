"""PNG rendering (matplotlib Agg, no ROS): bird's-eye frames and per-vehicle side/top views."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gd_completion.atomic import atomic_path
from gd_completion.geometry import Box3D, box_corners

INPUT_COLOUR = "#2b6cb0"
COMPLETION_COLOUR = "#e53e3e"
REFERENCE_COLOUR = "#718096"
MAX_BACKGROUND_POINTS = 200_000


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _xyz(points: np.ndarray | None) -> np.ndarray:
    if points is None:
        return np.zeros((0, 3), np.float32)
    if points.dtype.names:
        return np.stack([points["x"], points["y"], points["z"]], axis=1).astype(np.float32)
    return np.asarray(points, dtype=np.float32).reshape(-1, 3)


def _save(fig, path: str | Path) -> Path:
    path = Path(path)
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=fig.dpi)
    finally:
        _pyplot().close(fig)
    return path


def render_birdseye(path: str | Path, points: np.ndarray, boxes: Sequence[Box3D] = (),
                    completion: np.ndarray | None = None, *, extent: float | None = None,
                    title: str | None = None) -> Path:
    """Top view of a frame: input points (grey-blue, by height), box outlines and completed points (red)."""
    plt = _pyplot()
    xyz = _xyz(points)
    if len(xyz) > MAX_BACKGROUND_POINTS:
        xyz = xyz[np.random.default_rng(0).choice(len(xyz), MAX_BACKGROUND_POINTS, replace=False)]
    comp = _xyz(completion)
    fig, ax = plt.subplots(figsize=(9, 9), dpi=110)
    ax.scatter(xyz[:, 0], xyz[:, 1], s=0.2, c=INPUT_COLOUR, alpha=0.35, linewidths=0, rasterized=True)
    for box in boxes:
        corners = box_corners(box)[[0, 1, 2, 3, 0], :2]
        ax.plot(corners[:, 0], corners[:, 1], color="#dd6b20", lw=1.0)
        front = box_corners(box)[[0, 1], :2].mean(axis=0)
        ax.plot([box.center[0], front[0]], [box.center[1], front[1]], color="#dd6b20", lw=1.0)
    if len(comp):
        ax.scatter(comp[:, 0], comp[:, 1], s=0.6, c=COMPLETION_COLOUR, linewidths=0, rasterized=True)
    if extent is None and boxes:  # most boxes, at most 80 m (distant boxes would shrink everything)
        reach = np.abs(np.array([b.center for b in boxes])[:, :2]).max(axis=1)
        extent = float(np.clip(np.percentile(reach, 90) + 10.0, 20.0, 80.0))
    if extent is not None:
        ax.set_xlim(-extent, extent)
        ax.set_ylim(-extent, extent)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or f"{len(xyz)} points, {len(boxes)} boxes, {len(comp)} completed points")
    fig.tight_layout()
    return _save(fig, path)


def render_vehicles(path: str | Path,
                    items: Sequence[tuple[str, np.ndarray, np.ndarray | None, np.ndarray | None]],
                    *, max_columns: int = 4) -> Path:
    """Per vehicle, side (x-z) and top (x-y) views of input (blue), completion (red), reference (grey).

    `items`: (title, input_points, completion_points, reference_points or None), all (N, 3) in one frame
    per vehicle (e.g. the normalised box frame). Each vehicle gets a column with the side view above the top.
    """
    plt = _pyplot()
    items = list(items)
    if not items:
        raise ValueError("render_vehicles needs at least one vehicle")
    columns = min(max_columns, len(items))
    rows = -(-len(items) // columns)
    fig, axes = plt.subplots(2 * rows, columns, figsize=(3.6 * columns, 3.8 * rows), dpi=110, squeeze=False)
    for ax in axes.flat:
        ax.set_axis_off()
    for k, (title, partial, completion, reference) in enumerate(items):
        r, c = divmod(k, columns)
        clouds = [(_xyz(reference), REFERENCE_COLOUR, 0.5, "reference"),
                  (_xyz(completion), COMPLETION_COLOUR, 0.8, "completion"),
                  (_xyz(partial), INPUT_COLOUR, 1.5, "input")]
        stacked = np.concatenate([cl for cl, *_ in clouds]) if any(len(cl) for cl, *_ in clouds) else np.zeros((1, 3))
        lo, hi = stacked.min(axis=0), stacked.max(axis=0)
        centre, half = (lo + hi) / 2.0, (hi - lo) / 2.0 * 1.1 + 0.02 * float((hi - lo).max()) + 1e-3
        for row, (a, b, name) in enumerate(((0, 2, "side"), (0, 1, "top"))):
            ax = axes[2 * r + row, c]
            ax.set_axis_on()
            for cloud, colour, size, label in clouds:
                if len(cloud):
                    ax.scatter(cloud[:, a], cloud[:, b], s=size, c=colour, linewidths=0, label=label,
                               rasterized=True)
            ax.set_xlim(centre[a] - half[a], centre[a] + half[a])
            ax.set_ylim(centre[b] - half[b], centre[b] + half[b])
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            counts = f"in {len(clouds[2][0])}, out {len(clouds[1][0])}"
            ax.set_title(f"{title} ({name})\n{counts}" if row == 0 else f"{name}", fontsize=8)
    handles, labels = [], []
    for ax in axes.flat:
        h, lab = ax.get_legend_handles_labels()
        for hh, ll in zip(h, lab):
            if ll not in labels:
                handles.append(hh)
                labels.append(ll)
    if handles:
        fig.legend(handles, labels, loc="lower center", ncol=len(labels), markerscale=6, fontsize=8)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    return _save(fig, path)
