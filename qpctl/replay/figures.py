"""The figures beside the 3D view: what explains a run, over time, on one shared time axis.

From top to bottom: the clearance to the obstacles (and between the arm's own links) with d_safe and
d_influence; the tracking error; each joint's torque as a share of its limit (the torque itself
where the robot has no limits); the QP's status and the fallbacks that gave the torque, tick by tick
(and singular ticks, for every law). Every recorded sample is plotted. The page draws a cursor at
the time it shows and seeks where the figure is clicked, from the axes' place in the image
(:class:`Figure`).
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from qpctl.simulation.trajectory import Trajectory

WIDTH_PX = 560  # the image's width [px] (the page's side panel)
DPI = 100


@dataclass(frozen=True)
class Figure:
    """A PNG and where its time axis lies in it: time ``t0`` at ``left``, ``t1`` at ``right`` (fractions of
    the width), the panels spanning ``top`` to ``bottom`` (fractions of the height, from the top)."""

    png: bytes
    width: int
    height: int
    t0: float
    t1: float
    left: float
    right: float
    top: float
    bottom: float


def _runs(labels: np.ndarray) -> list[tuple[int, int, str]]:
    """(start, end, label) of each run of equal labels (end exclusive)."""
    if labels.size == 0:
        return []
    cut = np.flatnonzero(labels[1:] != labels[:-1]) + 1
    starts = np.concatenate([[0], cut])
    ends = np.concatenate([cut, [labels.size]])
    return [(int(a), int(b), str(labels[a])) for a, b in zip(starts, ends)]


def _status_rows(traj: Trajectory) -> list[tuple[str, np.ndarray, str]]:
    """(row label, mask over ticks, colour) of the status panel: each QP status, each fallback, singular."""
    rows: list[tuple[str, np.ndarray, str]] = []
    if traj.qp_status is not None:
        status = np.asarray(traj.qp_status).astype(str)
        for name in sorted(set(status.tolist()), key=lambda s: (s != "solved", s)):
            rows.append((f"QP {name}", status == name, "tab:green" if name == "solved" else "tab:red"))
    if traj.qp_fallback is not None:
        fb = np.asarray(traj.qp_fallback).astype(str)
        for name in sorted(set(fb.tolist()) - {""}):
            rows.append((f"fallback: {name}", fb == name, "tab:orange"))
    singular = np.asarray(traj.singular, bool)
    if singular.any():
        rows.append(("singular", singular, "tab:purple"))
    return rows


def explain(traj: Trajectory, *, d_safe: float, d_influence: float, tau_max: np.ndarray) -> Figure:
    """The figure of a run (module docstring): clearance [m], tracking error [m], torque against its
    limit, status per tick."""
    t = np.asarray(traj.t, float)
    rows = _status_rows(traj)
    heights = [2.0, 1.2, 1.6] + ([0.2 + 0.2 * len(rows)] if rows else [])
    gap, top, bottom = 0.22, 0.08, 0.45  # [in] between panels, above the first, below the last (the t axis)
    size = (WIDTH_PX / DPI, sum(heights) + gap * (len(heights) - 1) + top + bottom)
    fig, axes = plt.subplots(len(heights), 1, figsize=size, dpi=DPI, sharex=True, height_ratios=heights, squeeze=False)
    fig.subplots_adjust(left=0.15, right=0.98, top=1 - top / size[1], bottom=bottom / size[1],
                        hspace=gap / (sum(heights) / len(heights)))  # fixed margins: no tight_layout pass
    ax = axes[:, 0]
    # clearance, with d_safe and d_influence
    clear = np.asarray(traj.clearance, float)
    if np.isfinite(clear).any():
        ax[0].plot(t, clear, lw=1.1, color="tab:blue", label="to the obstacles")
    if traj.self_clearance is not None and np.isfinite(traj.self_clearance).any():
        ax[0].plot(t, traj.self_clearance, lw=0.9, color="tab:gray", label="between the links")
    ax[0].axhline(d_safe, color="tab:red", ls="--", lw=1.0, label=f"d_safe {d_safe:g} m")
    ax[0].axhline(d_influence, color="goldenrod", ls=":", lw=1.0, label=f"d_influence {d_influence:g} m")
    ax[0].axhline(0.0, color="k", lw=0.6)
    finite = clear[np.isfinite(clear)]
    low = min(0.0, float(finite.min())) if finite.size else 0.0
    # up to 3 d_influence (where the interesting part is), or the whole range if the run stays beyond it
    top = float(finite.max()) if finite.size else 3 * d_influence
    high = min(top, 3 * d_influence)
    if finite.size and float(finite.min()) >= 0.8 * high:
        high = top
    high = max(1.05 * high, 1.3 * d_influence)
    ax[0].set_ylim(low - 0.06 * (high - low), high)
    ax[0].set_ylabel("clearance [m]")
    ax[0].legend(loc="upper right", fontsize="x-small", ncol=2)
    # tracking error
    err = np.linalg.norm(np.asarray(traj.x_ref) - np.asarray(traj.x), axis=1)
    ax[1].semilogy(t, np.maximum(err, 1e-9), lw=1.0, color="tab:blue")
    ax[1].set_ylabel("tracking error [m]")
    # torques against their limits
    tau = np.asarray(traj.tau, float)
    limits = np.asarray(tau_max, float)
    if np.all(np.isfinite(limits)) and np.all(limits > 0):
        for j in range(tau.shape[1]):
            ax[2].plot(t, np.abs(tau[:, j]) / limits[j], lw=0.9, label=f"{j + 1}")
        ax[2].axhline(1.0, color="tab:red", ls="--", lw=1.0)
        ax[2].set_ylabel("|τ| / τ_max")
        ax[2].set_ylim(0.0, max(1.45, float(np.max(np.abs(tau) / limits)) * 1.05))  # the legend above the limit
    else:
        for j in range(tau.shape[1]):
            ax[2].plot(t, tau[:, j], lw=0.9, label=f"{j + 1}")
        ax[2].set_ylabel("τ [N·m] (no limit)")
    ax[2].legend(loc="upper right", fontsize="x-small", ncol=min(tau.shape[1], 7), title="joint",
                 title_fontsize="x-small")
    # status and fallbacks, tick by tick
    if rows:
        for r, (label, mask, colour) in enumerate(rows):
            for a, b, value in _runs(mask.astype(np.int8)):
                if value == "1":
                    ax[3].hlines(r, t[a], t[b - 1] if b - 1 > a else t[a] + 1e-3, colors=colour, lw=6)
        ax[3].set_yticks(range(len(rows)), [r[0] for r in rows], fontsize="x-small")
        ax[3].set_ylim(len(rows) - 0.5, -0.5)
    for a in ax:
        a.grid(alpha=0.3)
        a.tick_params(labelsize="x-small")
        a.yaxis.label.set_size("small")
    ax[-1].set_xlabel("t [s]", fontsize="small")
    ax[-1].set_xlim(float(t[0]), float(t[-1]) if t[-1] > t[0] else float(t[0]) + 1e-3)
    width, height = fig.canvas.get_width_height()
    first, last = ax[0].get_position(), ax[-1].get_position()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    plt.close(fig)
    x0, x1 = ax[-1].get_xlim()
    return Figure(buf.getvalue(), width, height, float(x0), float(x1), float(first.x0), float(first.x1),
                  1.0 - float(first.y1), 1.0 - float(last.y0))
