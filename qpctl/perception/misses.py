"""Why a reachable fruit was not reached: the closed loop's account of each miss (issue 21: "a fruit it
cannot reach is reported with the reason").

A canopy's fruits that no collision-free configuration reaches are reported when the canopy is grown
(:attr:`qpctl.scenes.canopy.Fruit.reason`). The others are the path's waypoints; a run with the
camera then misses some of them (the task point never within 5 mm). :func:`explain_misses` reads the
run's own records and names, for each miss, the first of these that holds:

1. **the reference never came**: the waiting reference (``perception.lag_*``, ``stale_*``) had not
   brought x_d within the tolerance by the run's end — whether it was still waiting (its progress
   rate κ < 1) and the task point's lag at the end are given, and what held the task point there
   (``held_by``: 2–4 below tested at the run's last tick, "" when none holds — a leaf's speed rows or
   the task's weight, which the records do not name);
2. **the QP gave up there**: a fallback acted on a tick within 0.1 s of the closest approach;
3. **a joint at its limit** at the closest approach (within 0.01 rad);
4. **held by the rigid rows' margin**: the map's rigid clearance (what the rows believed) within
   5 mm of the rigid rows' margin at the closest approach, with the true rigid clearance beside it
   (a map that believed a surface nearer than any there is says so);
5. **lagged**: none of these; the task point trailed its reference past the fruit (soft speed rows in
   a leaf, torque or rate limits) — the closest distance and the lag are given.

Each miss is a dict: ``fruit`` (index in path order, 0 = the first fruit), ``error_mm``, ``t_s`` (the
closest approach), ``cause`` (one of :data:`CAUSES`) and ``reason`` (a sentence with the numbers).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

CAUSES = ("reference", "fallback", "joint_limit", "rigid_margin", "lagged")
FALLBACK_WINDOW = 0.1  # [s] a fallback this near the closest approach is its cause
LIMIT_TOL = 0.01  # [rad]
MARGIN_TOL = 5e-3  # [m]


def explain_misses(points: np.ndarray, t: np.ndarray, x: np.ndarray, x_ref: np.ndarray, q: np.ndarray, *,
                   q_min: np.ndarray, q_max: np.ndarray, clearance: np.ndarray, fallback: np.ndarray | None,
                   believed: np.ndarray, margin: float, kappa: np.ndarray, tol: float = 5e-3) -> list[dict[str, Any]]:
    """Every fruit (``points`` (k, 3) [m], path order) whose least distance to the task point ``x``
    (T, ≥3) exceeds ``tol`` [m], with its cause. ``t`` (T,) [s]; ``x_ref`` the reference (T, ≥3);
    ``q`` (T, n) and its limits; ``clearance`` the true rigid clearance (T,) [m]; ``fallback`` each
    tick's fallback word ("" none; None: a closed form); ``believed`` the map's rigid clearance the
    rows read (T,) [m] (inf: none); ``margin`` the rigid rows' margin [m]; ``kappa`` the waiting
    reference's progress rate per tick."""
    out: list[dict[str, Any]] = []
    T = len(t)
    behind = np.linalg.norm(x[:T, :3] - x_ref[:T, :3], axis=1)  # |x − x_d| [m]
    for k, p in enumerate(np.asarray(points, float)):
        err = np.linalg.norm(x[:T, :3] - p, axis=1)
        i = int(np.argmin(err))
        if err[i] <= tol:
            continue
        miss: dict[str, Any] = {"fruit": k, "error_mm": float(err[i] * 1e3), "t_s": float(t[i])}
        ref = float(np.min(np.linalg.norm(x_ref[:T, :3] - p, axis=1)))
        cause, what, b = _holder(i, t, q, q_min, q_max, fallback, believed, margin, T)
        if ref > tol:
            miss["cause"] = "reference"
            why = (f"the path was waiting (κ {kappa[-1]:.2f} at the end" if kappa[-1] < 1.0 - 1e-9 else
                   "the path had not come to it yet (κ 1 at the end: at full pace after its waits")
            held, held_what, held_b = _holder(T - 1, t, q, q_min, q_max, fallback, believed, margin, T)
            miss["held_by"] = held
            held_words = {"fallback": f"a fallback ({held_what})", "joint_limit": f"joint {held_what} at its limit",
                          "rigid_margin": f"the rigid rows' margin (the map's rigid clearance {held_b * 1e3:.0f} mm)"}
            miss["reason"] = (f"the reference never came within {tol * 1e3:.0f} mm (closest {ref * 1e3:.0f} mm) by the "
                              f"run's end at {t[T - 1]:.1f} s: {why}, the task point {behind[-1] * 1e3:.0f} mm behind "
                              "its reference); at the end held by "
                              + held_words.get(held, "none of a fallback, a joint limit or the rigid rows' margin"))
        elif cause == "fallback":
            miss["cause"] = "fallback"
            miss["reason"] = f"the QP failed within {FALLBACK_WINDOW:.1f} s of the closest approach ({what})"
        elif cause == "joint_limit":
            miss["cause"] = "joint_limit"
            miss["reason"] = f"joint {what} at its limit at the closest approach"
        elif cause == "rigid_margin":
            truth = float(clearance[i])
            miss["cause"] = "rigid_margin"
            miss["reason"] = (f"held by the rigid rows' margin ({margin * 1e3:.0f} mm): the map's rigid clearance "
                              f"{b * 1e3:.0f} mm at the closest approach, the true rigid clearance {truth * 1e3:.0f} mm"
                              + (" (the map saw a surface nearer than any there is)" if truth > b + margin else ""))
        else:
            miss["cause"] = "lagged"
            miss["reason"] = (f"the task point trailed its reference past the fruit (closest {err[i] * 1e3:.0f} mm at "
                              f"{t[i]:.1f} s, {behind[i] * 1e3:.0f} mm behind it then)")
        out.append(miss)
    return out


def _holder(i: int, t: np.ndarray, q: np.ndarray, q_min: np.ndarray, q_max: np.ndarray, fallback: np.ndarray | None,
            believed: np.ndarray, margin: float, T: int) -> tuple[str, str, float]:
    """What holds the task point at tick ``i``, the first of causes 2–4 (module docstring): (cause,
    what — the fallbacks' words, or the joints at a limit as "j (lower|upper)" —, the map's rigid
    clearance the rows read [m]); cause "" when none holds."""
    b = float(believed[i]) if i < len(believed) else math.inf
    near = np.abs(t[:T] - t[i]) <= FALLBACK_WINDOW
    fb = [] if fallback is None else sorted({str(f) for f in np.asarray(fallback)[:T][near] if f})
    if fb:
        return "fallback", ", ".join(fb), b
    lo, hi = q[i] - q_min, q_max - q[i]
    at_limit = np.flatnonzero((lo < LIMIT_TOL) | (hi < LIMIT_TOL))
    if at_limit.size:
        return "joint_limit", ", ".join(f"{j + 1} ({'lower' if lo[j] < LIMIT_TOL else 'upper'})" for j in at_limit), b
    if b <= margin + MARGIN_TOL:
        return "rigid_margin", "", b
    return "", "", b
