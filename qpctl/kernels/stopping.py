"""The jerk-limited stopping distance of a point, and the largest closing acceleration that keeps the
next state able to stop (issue 22, item 1). Scalar kernels, compiled, called by the tick's rows
(:mod:`qpctl.kernels.rows`) and by the Python reference path (:mod:`qpctl.constraints`) alike.

A point closes on an obstacle (or a joint on its limit) at speed v [m/s] with closing acceleration a
[m/s²]. The brake can decelerate it at up to A [m/s²] and change its acceleration at up to J [m/s³]
(the torque-rate limit seen at the point). The brake ramps the acceleration down at −J until it
reaches −A, then holds −A until the point is at rest:

    t₁ = (a + A)/J,  v₁ = v + a t₁ − J t₁²/2,
    D(v, a) = v t₁ + a t₁²/2 − J t₁³/6 + v₁²/(2A)          while v₁ ≥ 0, i.e. v ≥ (A² − a²)/(2J),
    D(v, a) = v t* + a t*²/2 − J t*³/6,  t* = (a + √(a² + 2Jv))/J   otherwise (at rest before −A).

(Issue 22 writes the first case expanded.) a = −A gives v²/(2A); J = ∞ gives v²/(2A) for every a.
A closing acceleration below −A is taken as −A (D grows with a, so this over-estimates); a point
moving away (v < 0) that will turn towards the obstacle is followed through its turn; D ≥ 0 always.
The tests hold D against a fine integration of the braked point (``tests/test_stopping.py``).

:func:`max_closing_acceleration` is the row's bound: the largest a such that, after one period Δt at
a, the point can still stop within what is left, one more period of latency included:

    h − vΔt − aΔt²/2 − D(v + aΔt, a) − (v + aΔt)⁺Δt − v_o (2Δt + T(v + aΔt, a)) ≥ margin,

with v_o ≥ 0 the obstacle's own closing speed, which no brake of the arm removes (T: the time to rest).
The left side decreases in a, so the set of safe a is {a ≤ a*}: the bound is exact, not a linearisation,
and the row stays linear in q̈ (a = −ḧ).
"""

from __future__ import annotations

import math

from numba import njit

#: Bisection-safeguarded Newton: iterations, and the tolerance on a [m/s²] relative to 1 + |a|.
ITERATIONS = 60
TOLERANCE = 1e-13


@njit(cache=True)
def stopping(v: float, a: float, A: float, J: float) -> tuple[float, float, float, float, float]:
    """(D [m], ∂D/∂a [m·s²], T [s], ∂T/∂a [s³/m], ∂T/∂v [s²/m]): the distance and time to rest of the
    jerk-limited brake from closing speed v [m/s] and closing acceleration a [m/s²], deceleration
    A > 0 [m/s²], jerk J > 0 [m/s³] (inf: none) (module docstring). ∂D/∂v is T (the envelope)."""
    a = max(a, -A)
    if not J < math.inf:  # no rate limit: −A at once
        if v <= 0.0:
            return 0.0, 0.0, 0.0, 0.0, 0.0
        return v * v / (2.0 * A), 0.0, v / A, 0.0, 1.0 / A
    t1 = (a + A) / J
    v1 = v + a * t1 - 0.5 * J * t1 * t1
    if v1 >= 0.0:
        d = v * t1 + 0.5 * a * t1 * t1 - J * t1 * t1 * t1 / 6.0 + v1 * v1 / (2.0 * A)
        if d <= 0.0:
            return 0.0, 0.0, 0.0, 0.0, 0.0
        return d, (v + a * t1) / J + v1 * a / (A * J), t1 + v1 / A, 1.0 / J + a / (A * J), 1.0 / A
    disc = a * a + 2.0 * J * v
    if disc < 0.0:  # moving away, and it never turns towards the obstacle before −A
        return 0.0, 0.0, 0.0, 0.0, 0.0
    root = math.sqrt(disc)
    ts = (a + root) / J
    if ts <= 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0
    d = v * ts + 0.5 * a * ts * ts - J * ts * ts * ts / 6.0
    if d <= 0.0 or root <= 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0
    return d, 0.5 * ts * ts, ts, (1.0 + a / root) / J, 1.0 / root


@njit(cache=True)
def next_slack(a: float, h: float, v: float, vo: float, dt: float, A: float, J: float,
               margin: float) -> tuple[float, float]:
    """(F(a), F'(a)): what is left [m] after one period at closing acceleration a [m/s²] and the stop
    from there (module docstring), and its derivative in a."""
    v1 = v + a * dt
    d, d_a, t, t_a, t_v = stopping(v1, a, A, J)
    lat = v1 * dt if v1 > 0.0 else 0.0
    dlat = dt * dt if v1 > 0.0 else 0.0
    f = h - v * dt - 0.5 * a * dt * dt - d - lat - vo * (2.0 * dt + t) - margin
    fp = -0.5 * dt * dt - t * dt - d_a - dlat - vo * (t_a + t_v * dt)  # ∂D/∂v = T
    return f, fp


@njit(cache=True)
def max_closing_acceleration(h: float, v: float, vo: float, dt: float, A: float, J: float,
                             margin: float, a_cap: float) -> float:
    """The largest closing acceleration a* [m/s²] in [−a_cap, a_cap] with F(a*) ≥ 0 (F:
    :func:`next_slack`; h [m] the clearance beyond d_safe, v [m/s] the arm's closing speed, vo ≥ 0
    [m/s] the obstacle's, dt [s], A [m/s²], J [m/s³], margin [m]); −a_cap where even that is not
    enough (the row then asks for the hardest braking it may), a_cap where a_cap is safe."""
    lo, hi = -a_cap, a_cap
    f_hi, _ = next_slack(hi, h, v, vo, dt, A, J, margin)
    if f_hi >= 0.0:
        return hi
    f_lo, _ = next_slack(lo, h, v, vo, dt, A, J, margin)
    if f_lo <= 0.0:
        return lo
    a = lo
    for _ in range(ITERATIONS):
        f, fp = next_slack(a, h, v, vo, dt, A, J, margin)
        if f >= 0.0:
            lo = a
        else:
            hi = a
        if hi - lo <= TOLERANCE * (1.0 + abs(lo)):
            break
        step = a - f / fp if fp < 0.0 else 0.5 * (lo + hi)
        a = step if lo < step < hi else 0.5 * (lo + hi)
    return lo
