"""Figures of a run: joint torques, the arm's configurations over the obstacles, tracking error.

:func:`write_figures` writes one run's figures; :func:`torque_comparison` and
:func:`configuration_panels` put several runs side by side (the paper reproduction's Figs. 1–4).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from qpctl.geometry.obstacles import Obstacle
from qpctl.simulation.simulator import Trajectory


def plot_torques(ax: plt.Axes, traj: Trajectory, title: str = "") -> None:
    for j in range(traj.tau.shape[1]):
        ax.plot(traj.t, traj.tau[:, j], label=f"τ{j + 1}")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("torque [N·m]")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    if title:
        ax.set_title(title)


def plot_torque_rates(ax: plt.Axes, traj: Trajectory, tau_rate_max: np.ndarray | None = None) -> None:
    """|τ̇| per joint [N·m/s] (torques differenced tick to tick, log scale) and the drives' rate limit."""
    if traj.t.size < 2:
        return
    rate = np.abs(np.diff(traj.tau, axis=0)) / np.diff(traj.t)[:, None]
    for j in range(rate.shape[1]):
        ax.semilogy(traj.t[1:], np.maximum(rate[:, j], 1e-3), lw=0.8, label=f"|τ̇{j + 1}|")
    if tau_rate_max is not None and np.any(np.isfinite(tau_rate_max)):
        for lim in sorted(set(np.asarray(tau_rate_max)[np.isfinite(tau_rate_max)].tolist())):
            ax.axhline(lim, color="k", ls="--", lw=1.0)
        ax.text(traj.t[-1], float(np.nanmin(np.where(np.isfinite(tau_rate_max), tau_rate_max, np.nan))),
                "rate limit", ha="right", va="bottom", fontsize="small")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("torque rate [N·m/s]")
    ax.grid(alpha=0.3, which="both")


def draw_obstacles(ax: plt.Axes, obstacles: Sequence[Obstacle], t: float = 0.0) -> None:
    """Obstacles in the x–y plane at time t [s], each as its shape's patch (:mod:`qpctl.geometry.shapes`:
    boxes as rectangles, spheres, capsules and cylinders as circles)."""
    for o in obstacles:
        c = o.position_at(t)
        ax.add_patch(o.kind.patch(o, c, color="tab:red", alpha=0.4))
        if o.name:
            ax.annotate(o.name, (c[0], c[1]), ha="center", va="center", fontsize=8)


def plot_configurations(ax: plt.Axes, traj: Trajectory, segments: np.ndarray, obstacles: Sequence[Obstacle],
                        every: int = 200, title: str = "", mark_collisions: bool = False) -> None:
    """The paper's figure style: the arm drawn every ``every`` samples, the path, the obstacles.

    ``segments``: (T, L, 2, 3) link axes over time. With ``mark_collisions``, the configurations
    drawn while a link penetrates an obstacle (``traj.clearance`` < 0) are red, and the first
    colliding configuration is drawn whether or not it falls on the ``every`` grid.
    """
    draw_obstacles(ax, obstacles)
    idx = list(range(0, len(traj.t), every)) + [len(traj.t) - 1]
    hit = np.flatnonzero(traj.clearance < 0) if mark_collisions else np.zeros(0, int)
    if hit.size:
        idx = sorted(set(idx) | {int(hit[0])})
    for k, i in enumerate(idx):
        shade = 0.25 + 0.75 * k / max(len(idx) - 1, 1)
        pts = np.vstack([segments[i, 0, 0], segments[i, :, 1]])
        colliding = mark_collisions and traj.clearance[i] < 0
        color = (0.85, 0.1, 0.1, max(shade, 0.6)) if colliding else (0.1, 0.2, 0.6, shade)
        ax.plot(pts[:, 0], pts[:, 1], "-o", color=color, ms=2, lw=1.4 if colliding else 1)
    ax.plot(traj.x_ref[:, 0], traj.x_ref[:, 1], "--", color="tab:green", lw=1, label="reference")
    ax.plot(traj.x[:, 0], traj.x[:, 1], "-", color="tab:orange", lw=1, label="end effector")
    if hit.size:
        ax.plot([], [], "-", color=(0.85, 0.1, 0.1), lw=1.4, label="in collision")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    if title:
        ax.set_title(title)


def plot_tracking(ax: plt.Axes, traj: Trajectory, title: str = "") -> None:
    err = np.linalg.norm(traj.x_ref - traj.x, axis=1)
    ax.semilogy(traj.t, np.maximum(err, 1e-12))
    ax.set_xlabel("t [s]")
    ax.set_ylabel("‖x_d − x‖ [m]")
    ax.grid(alpha=0.3, which="both")
    if title:
        ax.set_title(title)


def write_figures(out: Path, traj: Trajectory, segments: np.ndarray, obstacles: Sequence[Obstacle],
                  label: str, tau_rate_max: np.ndarray | None = None) -> list[Path]:
    """Write torques.png (torques, and their rates against the drives' rate limit),
    configurations.png (planar robots) and tracking.png into ``out``."""
    files = []
    fig, (ax, ax_rate) = plt.subplots(2, 1, figsize=(7, 6), sharex=True, height_ratios=[3, 2])
    plot_torques(ax, traj, f"joint torques — {label}")
    ax.set_xlabel("")
    plot_torque_rates(ax_rate, traj, tau_rate_max)
    files.append(out / "torques.png")
    fig.tight_layout()
    fig.savefig(files[-1], dpi=120)
    plt.close(fig)
    if segments.shape[-1] == 3 and np.allclose(segments[..., 2], 0):
        fig, ax = plt.subplots(figsize=(6, 6))
        plot_configurations(ax, traj, segments, obstacles, every=max(len(traj.t) // 25, 1),
                            title=f"configurations — {label}")
        files.append(out / "configurations.png")
        fig.tight_layout()
        fig.savefig(files[-1], dpi=120)
        plt.close(fig)
    extra = [traj.orientation_error_deg is not None, bool(np.isfinite(traj.clearance).any())
             or traj.self_clearance is not None]
    fig, axes = plt.subplots(1 + sum(extra), 1, figsize=(7, 3.5 + 2.5 * sum(extra)), sharex=True, squeeze=False)
    panels = list(axes[:, 0])
    plot_tracking(panels[0], traj, f"tracking error — {label}")
    k = 1
    if extra[0]:  # the orientation task's angle (the approach axis's for an approach task)
        assert traj.orientation_error_deg is not None
        panels[k].semilogy(traj.t, np.maximum(traj.orientation_error_deg, 1e-9))
        panels[k].set_ylabel("orientation error [°]")
        panels[k].grid(alpha=0.3, which="both")
        k += 1
    if extra[1]:  # clearances to the obstacles and between the arm's own links
        if np.isfinite(traj.clearance).any():
            panels[k].plot(traj.t, traj.clearance, label="to the obstacles")
        if traj.self_clearance is not None:
            panels[k].plot(traj.t, traj.self_clearance, label="between the links")
        panels[k].axhline(0.0, color="r", lw=0.8)
        panels[k].set_ylabel("clearance [m]")
        panels[k].legend(loc="upper right")
        panels[k].grid(alpha=0.3)
    for ax in panels[:-1]:
        ax.set_xlabel("")
    panels[-1].set_xlabel("t [s]")
    files.append(out / "tracking.png")
    fig.tight_layout()
    fig.savefig(files[-1], dpi=120)
    plt.close(fig)
    return files


def save_compact(fig: plt.Figure, path: Path, dpi: int) -> Path:
    """Save ``fig`` as a palette PNG (256 colours): a third of the size of matplotlib's RGBA file for
    line plots, so that the figures stay small enough to keep in the repository."""
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return compact_png(path)


def compact_png(path: Path, *, octree: bool = False) -> Path:
    """Rewrite the PNG at ``path`` as a palette PNG (256 colours, no dithering; ``octree``: PIL's octree
    palette, which keeps a small patch of a distinct colour — a screenshot's marker — where median cut
    merges it into its neighbours)."""
    from PIL import Image

    with Image.open(path) as img:
        method = Image.Quantize.FASTOCTREE if octree else Image.Quantize.MEDIANCUT
        small = img.convert("RGB").quantize(colors=256, method=method, dither=Image.Dither.NONE)
    small.save(path, optimize=True)
    return Path(path)


def torque_comparison(runs: Sequence[tuple[str, Trajectory]], path: Path, *, zoom: float = 1.0,
                      dpi: int = 100) -> Path:
    """Joint torques of several runs side by side (the paper's Figs. 1–2): the whole run on top, the
    first ``zoom`` seconds below, each row on a shared torque axis so the columns compare directly."""
    fig, axes = plt.subplots(2, len(runs), figsize=(4.6 * len(runs), 6.2), sharey="row", squeeze=False)
    for col, (label, traj) in enumerate(runs):
        plot_torques(axes[0, col], traj, label)
        plot_torques(axes[1, col], traj, f"{label}: first {zoom:g} s")
        axes[1, col].set_xlim(0.0, zoom)
        for row in range(2):
            if col:
                axes[row, col].set_ylabel("")
                axes[row, col].get_legend().remove()
    if runs:
        k = int(np.searchsorted(runs[0][1].t, zoom, side="right"))
        lo = min(float(np.min(tr.tau[:k])) for _, tr in runs)
        hi = max(float(np.max(tr.tau[:k])) for _, tr in runs)
        pad = 0.05 * max(hi - lo, 1.0)
        axes[1, 0].set_ylim(lo - pad, hi + pad)
    fig.tight_layout()
    return save_compact(fig, path, dpi)


def configuration_panels(panels: Sequence[tuple[str, Trajectory, np.ndarray]], obstacles: Sequence[Obstacle],
                         path: Path, *, snapshots: int = 24, ncols: int | None = None, dpi: int = 100) -> Path:
    """The arm's configurations over the obstacles for several runs side by side (Figs. 3–4 style);
    ``panels`` holds (title, trajectory, (T, L, 2, 3) link axes), laid out ``ncols`` to a row (all in
    one row by default). Colliding configurations are red."""
    ncols = ncols or len(panels)
    nrows = -(-len(panels) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.3 * ncols, 4.6 * nrows), sharex=True, sharey=True,
                             squeeze=False)
    flat = list(axes.flat)
    for ax, (title, traj, segments) in zip(flat, panels):
        every = max(len(traj.t) // snapshots, 1)
        plot_configurations(ax, traj, segments, obstacles, every=every, title=title, mark_collisions=True)
    for i, ax in enumerate(flat):
        if i >= len(panels):
            ax.set_visible(False)
            continue
        if i % ncols:
            ax.set_ylabel("")
        if i < len(panels) - ncols:
            ax.set_xlabel("")
        if i and ax.get_legend() is not None:
            ax.get_legend().remove()
    fig.tight_layout()
    return save_compact(fig, path, dpi)
