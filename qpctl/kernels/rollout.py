"""The arithmetic of a brake rollout's step (:mod:`qpctl.safety.rollout`), compiled: the brake's
clip, RK4's stages and sum, the state's checks. No rigid-body quantity is computed here (Pinocchio's
RNEA and ABA are called from Python between these); each kernel does in one call what would be a
dozen small numpy operations, in the same order of operations as
:func:`qpctl.simulation.simulator.rk4_step` so that the states equal the simulator's.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: :func:`state_code`'s answers.
MOVING, AT_REST, OUTSIDE = 0, 1, 2


@njit(cache=True)
def clip_brake(tau, tau_max, prev, window):  # type: ignore[no-untyped-def]
    """τ ← clip(clip(τ, ±τ_max), τ_prev ± window) in place; no rate window while τ_prev[0] is NaN
    (nothing applied yet). The order of the clips is the oracle's."""
    rate = np.isfinite(prev[0])
    for i in range(tau.shape[0]):
        x = min(max(tau[i], -tau_max[i]), tau_max[i])
        if rate:
            x = min(max(x, prev[i] - window[i]), prev[i] + window[i])
        tau[i] = x


@njit(cache=True)
def stage(q, v, kq, ka, h, dq, qs, vs):  # type: ignore[no-untyped-def]
    """A stage's state: dq ← h·kq, qs ← q + dq (a vector space; a Lie robot integrates dq itself),
    vs ← v + h·ka (rk4_step's ``v + 0.5 * dt * k1v``: the scalar product first)."""
    for i in range(v.shape[0]):
        vs[i] = v[i] + h * ka[i]
        dq[i] = h * kq[i]
    for i in range(q.shape[0]):
        qs[i] = q[i] + dq[i]


@njit(cache=True)
def combine(k, c, out):  # type: ignore[no-untyped-def]
    """out ← c·(((k₀ + 2k₁) + 2k₂) + k₃) (rk4_step's ``dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)``)."""
    for i in range(out.shape[0]):
        out[i] = c * (((k[0, i] + 2.0 * k[1, i]) + 2.0 * k[2, i]) + k[3, i])


@njit(cache=True)
def state_code(q, v, q_min, q_max, rest_speed):  # type: ignore[no-untyped-def]
    """OUTSIDE if a coordinate is not finite or a joint is beyond its limits, else AT_REST if every
    |q̇ᵢ| ≤ rest_speed [rad/s], else MOVING."""
    for i in range(q.shape[0]):
        if not np.isfinite(q[i]) or q[i] < q_min[i] or q[i] > q_max[i]:
            return OUTSIDE
    rest = True
    for i in range(v.shape[0]):
        if not np.isfinite(v[i]):
            return OUTSIDE
        if abs(v[i]) > rest_speed:
            rest = False
    return AT_REST if rest else MOVING


@njit(cache=True)
def travel(dq, rho):  # type: ignore[no-untyped-def]
    """Σᵢ ρᵢ|dqᵢ| [m]: a bound on how far any point of the links moves over a joint step dq [rad]."""
    s = 0.0
    for i in range(dq.shape[0]):
        s += rho[i] * abs(dq[i])
    return s


@njit(cache=True)
def stage_into(q, v, kq, ka, i, h, qs):  # type: ignore[no-untyped-def]
    """RK4 stage i + 1's state in one call (vector-space configurations): kq[0] ← v when i = 0,
    kq[i+1] ← v + h·ka[i] (its velocity), qs ← q + h·kq[i] (:func:`stage`'s operations)."""
    if i == 0:
        for j in range(v.shape[0]):
            kq[0, j] = v[j]
    for j in range(v.shape[0]):
        kq[i + 1, j] = v[j] + h * ka[i, j]
    for j in range(q.shape[0]):
        qs[j] = q[j] + h * kq[i, j]


@njit(cache=True)
def finish(q, v, kq, ka, c, dq, dv, rho):  # type: ignore[no-untyped-def]
    """The step's end in one call: dq, dv ← :func:`combine` of kq, ka; q += dq; v += dv; returns
    :func:`travel` (Σᵢ ρᵢ|dqᵢ|)."""
    combine(kq, c, dq)
    combine(ka, c, dv)
    for j in range(q.shape[0]):
        q[j] += dq[j]
    for j in range(v.shape[0]):
        v[j] += dv[j]
    return travel(dq, rho)


@njit(cache=True)
def settled(tau, nxt, tau_max, window, gain, dt, beta):  # type: ignore[no-untyped-def]
    """True if the brake's unclipped torque τ [N·m] is in its decay's linear regime: with ``nxt`` the
    torque one step ahead along q̇e^{−κt}, each joint's change d = |nxt − τ| within ``beta`` of its rate
    ``window`` [N·m a step] and |τ| + d/(κΔt) — the whole change if the rate decays with the speed —
    within ``beta`` of τ_max (brake_rollout.cpp's ``settled``, the same operations)."""
    for i in range(tau.shape[0]):
        d = abs(nxt[i] - tau[i])
        if not (d <= beta * window[i]) or not (abs(tau[i]) + d / (gain * dt) <= beta * tau_max[i]):
            return False
    return True


@njit(cache=True)
def stops_within(q, v, gain, q_min, q_max):  # type: ignore[no-untyped-def]
    """True if every joint's stop end q + q̇/κ lies within [q_min, q_max] (:func:`qpctl.safety.sweep.stops_within`)."""
    for i in range(q.shape[0]):
        end = q[i] + v[i] / gain
        if not (end >= q_min[i] and end <= q_max[i]):
            return False
    return True


@njit(cache=True)
def max_abs(v):  # type: ignore[no-untyped-def]
    """max |vᵢ|."""
    m = 0.0
    for i in range(v.shape[0]):
        m = max(m, abs(v[i]))
    return m
