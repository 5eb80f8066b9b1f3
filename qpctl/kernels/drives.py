"""What the drives can give this tick: the torque window and the range of a row it spans.

:func:`torque_window` is the torque a joint may be commanded this tick (±τ_max and the rate limit
about the last torque). :func:`row_range` is the range of c q̈ over that window, q̈ = M⁻¹(τ − N):
with y = M⁻¹cᵀ (M's Cholesky factor ``ws.Lm``), c q̈ = yᵀ(τ − N) is largest at τₖ = hiₖ where
yₖ > 0 and loₖ elsewhere, and least the other way round — the reach of one row alone, before the
joint-acceleration bounds and the other rows. The field's rigid rows inside their margin ask no
more than a share of it (:mod:`qpctl.kernels.field_rows`); the Python path's
:meth:`qpctl.perception.rows.FieldBarrier.compute` computes the same from
:meth:`qpctl.constraints.TorqueLimit.window`, and ``tests/test_field_rows.py`` holds both to
scipy's linear programme. :func:`box_cap` is the same share of a row's range within ±q̈_max, the
joints' acceleration limits: what a self-collision row inside self_d_safe asks at most
(:func:`qpctl.kernels.rows.self_rows`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from qpctl.kernels.codes import FP_T
from qpctl.kernels.small import chol_solve

#: A row inside its margin asks at most ℓ − ρ(ℓ − ℓ₋) of its range [ℓ₋, ℓ] this tick: ρ.
REACH_SHARE = 0.25


@njit(cache=True)
def torque_window(ws, i: int) -> tuple[float, float]:  # type: ignore[no-untyped-def]
    """The torque joint i may be commanded this tick [N·m]: within ±τ_max and, once a torque was
    commanded at t_prev < t, within τ_prev ± τ̇_max (t − t_prev). Where the two do not meet (τ_prev
    beyond τ_max: the limit changed) the torque limit wins (:func:`torque_window_at`)."""
    return torque_window_at(ws.tau_max[i], ws.tau_rate[i], ws.tau_prev[i], ws.fpar[FP_T] - ws.t_prev[0])


@njit(cache=True)
def torque_window_at(lim: float, rate: float, prev: float, dt: float) -> tuple[float, float]:
    """:func:`torque_window` of a joint with torque limit ``lim`` [N·m], rate limit ``rate`` [N·m/s]
    and last torque ``prev`` [N·m], dt = t − t_prev [s] (NaN: no torque commanded yet). Scalars: what
    a loop over the joints calls with its arrays held once (arrays passed or read per joint cost
    atomic reference counts each time)."""
    lo, hi = -lim, lim
    if dt > 0.0:  # False for NaN: no torque commanded yet
        w = rate * dt
        lo2, hi2 = max(lo, prev - w), min(hi, prev + w)
        if lo2 <= hi2:
            return lo2, hi2
    return lo, hi


@njit(cache=True)
def row_range(ws, c: np.ndarray, y: np.ndarray) -> tuple[float, float]:  # type: ignore[no-untyped-def]
    """(least, largest) c q̈ [its units] over this tick's torque window (module docstring); c (n,) a
    row on q̈, y (n,) scratch. Unbounded (±inf) where a torque limit is infinite."""
    n = ws.v.shape[0]
    for k in range(n):
        y[k] = c[k]
    chol_solve(ws.Lm, y)
    lo_sum, hi_sum = 0.0, 0.0
    for k in range(n):
        if y[k] == 0.0:
            continue
        lo, hi = torque_window(ws, k)
        a, b = y[k] * (lo - ws.N[k]), y[k] * (hi - ws.N[k])
        lo_sum += min(a, b)
        hi_sum += max(a, b)
    return lo_sum, hi_sum


@njit(cache=True)
def box_cap(ws, c: np.ndarray) -> float:  # type: ignore[no-untyped-def]
    """ℓ − ρ(ℓ − ℓ₋) = (1 − 2ρ)s (ρ = :data:`REACH_SHARE`) for [ℓ₋, ℓ] = ±s, s = Σₖ |cₖ| q̈_max,k, the
    range of c q̈ within the joints' acceleration limits (its first n entries read); +inf (no cap)
    where a joint the row moves has none."""
    s = 0.0
    for k in range(ws.v.shape[0]):
        if c[k] != 0.0:
            s += abs(c[k]) * ws.qdd_max[k]
    return (1.0 - 2.0 * REACH_SHARE) * s
