"""Figures of the depth map (``qpctl simulate`` writes them beside the run's with a ``[camera]``).

* :func:`depth_frame_figure` — one depth frame beside what the pipeline made of each pixel (kept,
  no return, out of range, flying, the robot's self-filter, the grasp target's zone, outside the map,
  the robot's shadow);
* :func:`field_slice_figure` — a horizontal slice of the distance field, both channels;
* :func:`clearance_figure` — the true rigid clearance against what the map's rows believed, over time.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg", force=False)
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import ListedColormap

from qpctl.kernels.depth import STATUS_NAMES
from qpctl.perception.frames import DepthFrame
from qpctl.perception.snapshot import MapSnapshot

STATUS_COLOURS = ("#2ca02c", "#dddddd", "#8c564b", "#ff7f0e", "#d62728", "#9467bd", "#1f77b4", "#e377c2")


def _save(fig: plt.Figure, path: Path, title: str) -> Path:
    """The figure, titled, laid out and written to ``path`` (then closed)."""
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def depth_frame_figure(path: Path, frame: DepthFrame, status: np.ndarray, title: str = "") -> Path:
    """The frame's depth [m] and each pixel's fate (the self-filter's pixels in red)."""
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.2))
    z = frame.metres().astype(float)
    z[~(np.isfinite(z) & (z > 0))] = np.nan
    im = a.imshow(z, cmap="viridis")
    fig.colorbar(im, ax=a, label="depth [m]", shrink=0.85)
    a.set_title(f"depth frame at t = {frame.stamp:.2f} s")
    cmap = ListedColormap(STATUS_COLOURS)
    b.imshow(status, cmap=cmap, vmin=-0.5, vmax=len(STATUS_NAMES) - 0.5, interpolation="nearest")
    counts = np.bincount(status.ravel(), minlength=len(STATUS_NAMES))
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in STATUS_COLOURS]
    # beside the image, not over it (the legend's pixel counts are the figure's numbers)
    b.legend(handles, [f"{n} ({k})" for n, k in zip(STATUS_NAMES, counts, strict=True)], loc="center left",
             bbox_to_anchor=(1.02, 0.5), fontsize=8, frameon=False)
    b.set_title("each pixel's fate")
    for ax in (a, b):
        ax.set_xticks([])
        ax.set_yticks([])
    return _save(fig, path, title)


def field_slice_figure(path: Path, snapshot: MapSnapshot, z: float, *, segments: np.ndarray | None = None,
                       title: str = "") -> Path:
    """The field of each channel at height ``z`` [m] (the voxel layer holding it), with the link axes
    (``segments`` (L, 2, 3) [m]) projected on it where given."""
    g = snapshot.grid
    k = int(np.clip(np.floor((z - g.origin[2]) / g.voxel), 0, g.shape[2] - 1))
    extent = (g.origin[0], g.upper[0], g.origin[1], g.upper[1])
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
    for ch, (ax, name) in enumerate(zip(axes, ("rigid", "soft"), strict=True)):
        im = ax.imshow(snapshot.dist[ch, :, :, k].T, origin="lower", extent=extent, cmap="magma",
                       vmin=0.0, vmax=snapshot.truncation)
        ax.contour(np.linspace(extent[0], extent[1], g.shape[0]), np.linspace(extent[2], extent[3], g.shape[1]),
                   snapshot.dist[ch, :, :, k].T, levels=[0.05, 0.1, 0.2], colors="w", linewidths=0.6)
        if segments is not None:
            for a, b in segments:
                ax.plot([a[0], b[0]], [a[1], b[1]], "c-", lw=2)
        ax.set_title(f"{name} channel, z = {g.origin[2] + (k + 0.5) * g.voxel:.2f} m")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        fig.colorbar(im, ax=ax, label="distance [m]", shrink=0.85)
    return _save(fig, path, title)


def clearance_figure(path: Path, t: np.ndarray, true: np.ndarray, believed: np.ndarray, d_safe: float,
                     margin: float, age_ms: np.ndarray | None = None, title: str = "") -> Path:
    """True rigid clearance [m] and the least distance the map's rigid rows believed [m] over t [s];
    the map's age [ms] below."""
    rows = 2 if age_ms is not None else 1
    fig, axes = plt.subplots(rows, 1, figsize=(9, 5.5 if rows == 2 else 3.5), sharex=True, squeeze=False)
    ax = axes[0, 0]
    ax.plot(t, true, label="true clearance (rigid geometry)")
    shown = np.where(np.isfinite(believed), believed, np.nan)
    ax.plot(t, shown, label="believed by the map's rows", alpha=0.8)
    ax.axhline(d_safe, color="k", ls="--", lw=0.8, label=f"d_safe = {d_safe:.3f} m")
    ax.axhline(margin, color="r", ls=":", lw=0.8, label=f"rigid rows' margin = {margin:.3f} m")
    ax.set_ylabel("clearance [m]")
    ax.set_ylim(bottom=min(0.0, float(np.nanmin(true))), top=max(0.35, float(np.nanmin(true)) + 0.05))
    ax.legend(fontsize=8)
    if age_ms is not None:
        axes[1, 0].plot(t, age_ms, color="tab:gray")
        axes[1, 0].set_ylabel("map age [ms]")
    axes[-1, 0].set_xlabel("t [s]")
    return _save(fig, path, title)
