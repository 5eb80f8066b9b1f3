"""Figures of a run: joint torques, the arm's configurations over the obstacles, tracking error."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from qpctl.geometry.obstacles import Obstacle  # noqa: E402
from qpctl.simulation.simulator import Trajectory  # noqa: E402


def plot_torques(ax: plt.Axes, traj: Trajectory, title: str = "") -> None:
    for j in range(traj.tau.shape[1]):
        ax.plot(traj.t, traj.tau[:, j], label=f"τ{j + 1}")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("torque [N·m]")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    if title:
        ax.set_title(title)


def draw_obstacles(ax: plt.Axes, obstacles: Sequence[Obstacle], t: float = 0.0) -> None:
    for o in obstacles:
        c = o.position_at(t)
        if o.shape == "box" and o.size is not None:
            ax.add_patch(plt.Rectangle((c[0] - o.size[0] / 2, c[1] - o.size[1] / 2), o.size[0], o.size[1],
                                       color="tab:red", alpha=0.4))
        else:
            ax.add_patch(plt.Circle((c[0], c[1]), o.radius, color="tab:red", alpha=0.4))
        if o.name:
            ax.annotate(o.name, (c[0], c[1]), ha="center", va="center", fontsize=8)


def plot_configurations(ax: plt.Axes, traj: Trajectory, segments: np.ndarray, obstacles: Sequence[Obstacle],
                        every: int = 200, title: str = "") -> None:
    """The paper's figure style: the arm drawn every ``every`` samples, the path, the obstacles.

    ``segments``: (T, L, 2, 3) link axes over time.
    """
    draw_obstacles(ax, obstacles)
    idx = list(range(0, len(traj.t), every)) + [len(traj.t) - 1]
    for k, i in enumerate(idx):
        shade = 0.25 + 0.75 * k / max(len(idx) - 1, 1)
        pts = np.vstack([segments[i, 0, 0], segments[i, :, 1]])
        ax.plot(pts[:, 0], pts[:, 1], "-o", color=(0.1, 0.2, 0.6, shade), ms=2, lw=1)
    ax.plot(traj.x_ref[:, 0], traj.x_ref[:, 1], "--", color="tab:green", lw=1, label="reference")
    ax.plot(traj.x[:, 0], traj.x[:, 1], "-", color="tab:orange", lw=1, label="end effector")
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
                  label: str) -> list[Path]:
    """Write torques.png, configurations.png (planar robots) and tracking.png into ``out``."""
    files = []
    fig, ax = plt.subplots(figsize=(7, 4))
    plot_torques(ax, traj, f"joint torques — {label}")
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
    fig, ax = plt.subplots(figsize=(7, 3.5))
    plot_tracking(ax, traj, f"tracking error — {label}")
    files.append(out / "tracking.png")
    fig.tight_layout()
    fig.savefig(files[-1], dpi=120)
    plt.close(fig)
    return files
