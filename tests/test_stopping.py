"""The jerk-limited stopping distance and the braking row's bound (qpctl.kernels.stopping, issue 22).

References: a fine integration of the braked point written here (the acceleration ramped at −J to −A,
held, the point followed until at rest: the largest distance it reaches), finite differences for the
derivatives, and the same integration for the row's bound (one period at a*, one period of latency,
then the brake, the obstacle closing on its own)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from qpctl.kernels.stopping import max_closing_acceleration, next_slack, stopping

SEED = 2201


def braked(v: np.ndarray, a: np.ndarray, A: np.ndarray, J: np.ndarray, *, hold: np.ndarray | None = None,
           dt: float = 2e-4, t_end: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """(largest distance travelled [m], time it is reached [s]) of points starting at speed v with
    acceleration a, holding a for ``hold`` [s] (default 0), then braking: jerk −J until −A, then −A,
    until at rest (each step integrates the piecewise-constant jerk exactly)."""
    x = np.zeros_like(v)
    vel, acc = v.astype(float).copy(), a.astype(float).copy()
    hold = np.zeros_like(v) if hold is None else hold
    best, when = np.zeros_like(v), np.zeros_like(v)
    moving = np.ones(v.shape, bool)
    t = 0.0
    while t < t_end and moving.any():
        braking = t >= hold
        acc = np.where(moving & braking, np.maximum(acc, -A), acc)  # the brake decelerates at A, no more
        ramp = braking & (acc > -A)
        h1 = np.where(ramp, np.minimum(dt, (acc + A) / J), 0.0)  # under jerk −J, then the rest at 0
        for h, jerk in ((h1, np.where(ramp, -J, 0.0)), (dt - h1, 0.0)):
            x = x + np.where(moving, vel * h + acc * h**2 / 2 + jerk * h**3 / 6, 0.0)
            vel = np.where(moving, vel + acc * h + jerk * h**2 / 2, vel)
            acc = np.where(moving, acc + jerk * h, acc)
        t += dt
        up = moving & (x > best)
        best, when = np.where(up, x, best), np.where(up, t, when)
        moving &= ~(braking & (vel <= 0) & (acc <= 0))
    assert not moving.any()
    return best, when


def cases(rng: np.random.Generator, k: int) -> tuple[np.ndarray, ...]:
    A = rng.uniform(3.0, 20.0, k)
    J = rng.uniform(5.0, 400.0, k)
    v = rng.uniform(-0.5, 3.0, k)
    a = rng.uniform(-1.5, 1.5, k) * A
    return v, a, A, J


def test_stopping_distance_equals_a_fine_integration():
    """D(v, a) and the time to rest against the braked point integrated at 0.2 ms, over 100 random
    (v, a, A, J) covering both branches, points moving away, and a below −A: |ΔD| ≤ 1e-6 m + 1e-5·D."""
    rng = np.random.default_rng(SEED)
    v, a, A, J = cases(rng, 100)
    want, t_want = braked(v, a, A, J)
    got = np.array([stopping(*c)[0] for c in zip(v, a, A, J, strict=True)])
    T = np.array([stopping(*c)[2] for c in zip(v, a, A, J, strict=True)])
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    far = want > 1e-3
    np.testing.assert_allclose(T[far], t_want[far], atol=4e-4)
    branch = v >= (A**2 - np.clip(a, -A, None) ** 2) / (2 * J)
    assert 10 < branch.sum() < 90 and (v < 0).sum() > 5 and (a < -A).sum() > 5


def test_stopping_distance_limits():
    """a = −A: v²/(2A); no rate limit: v²/(2A); at a = 0 the rate limit adds about v·A/(2J) (J large);
    at rest and not accelerating: 0."""
    for v, A in ((1.0, 5.0), (2.5, 12.0)):
        assert stopping(v, -A, A, 50.0)[0] == pytest.approx(v * v / (2 * A), rel=1e-12)
        assert stopping(v, 3.0, A, math.inf)[0] == pytest.approx(v * v / (2 * A), rel=1e-12)
        J = 1e5
        assert stopping(v, 0.0, A, J)[0] - v * v / (2 * A) == pytest.approx(v * A / (2 * J), rel=1e-3)
    assert stopping(0.0, 0.0, 5.0, 50.0)[0] == 0.0
    assert stopping(-1.0, -1.0, 5.0, 50.0)[0] == 0.0


def test_stopping_derivatives_equal_finite_differences():
    """∂D/∂a (returned), ∂D/∂v (the time to rest), the time's own derivatives and the row's F′ against
    central differences, away from D = 0."""
    rng = np.random.default_rng(SEED + 1)
    v, a, A, J = cases(rng, 300)
    checked = 0
    for vi, ai, Ai, Ji in zip(v, a, A, J, strict=True):
        d, dda, T, dta, dtv = stopping(vi, ai, Ai, Ji)
        if d < 1e-3 or abs(ai + Ai) < 1e-3 or ai < -Ai:
            continue
        e = 1e-6
        fd_a = (stopping(vi, ai + e, Ai, Ji)[0] - stopping(vi, ai - e, Ai, Ji)[0]) / (2 * e)
        fd_v = (stopping(vi + e, ai, Ai, Ji)[0] - stopping(vi - e, ai, Ai, Ji)[0]) / (2 * e)
        assert dda == pytest.approx(fd_a, rel=1e-5, abs=1e-8)
        assert T == pytest.approx(fd_v, rel=1e-5, abs=1e-8)
        fd_ta = (stopping(vi, ai + e, Ai, Ji)[2] - stopping(vi, ai - e, Ai, Ji)[2]) / (2 * e)
        fd_tv = (stopping(vi + e, ai, Ai, Ji)[2] - stopping(vi - e, ai, Ai, Ji)[2]) / (2 * e)
        assert dta == pytest.approx(fd_ta, rel=1e-5, abs=1e-8) and dtv == pytest.approx(fd_tv, rel=1e-5, abs=1e-8)
        _, fp = next_slack(ai, 1.0, vi, 0.2, 1e-3, Ai, Ji, 0.01)
        fd_f = (next_slack(ai + e, 1.0, vi, 0.2, 1e-3, Ai, Ji, 0.01)[0]
                - next_slack(ai - e, 1.0, vi, 0.2, 1e-3, Ai, Ji, 0.01)[0]) / (2 * e)
        assert fp == pytest.approx(fd_f, rel=1e-5, abs=1e-8)
        checked += 1
    assert checked > 150


def test_max_closing_acceleration_keeps_the_next_state_able_to_stop():
    """a* from random states: one period at a*, one period of latency at the acceleration reached,
    then the brake (the fine integration), the obstacle closing at v_o all along, leave the margin
    (to 1e-6 m and the time step's share of the obstacle's travel); 1 % more than an interior a* does not."""
    rng = np.random.default_rng(SEED + 2)
    k = 60
    v, _, A, J = cases(rng, k)
    h = rng.uniform(0.05, 1.5, k)
    vo = np.where(rng.random(k) < 0.3, rng.uniform(0.0, 0.3, k), 0.0)
    dt, margin, cap = 2e-3, 0.01, 3.0 * A
    star = np.array([max_closing_acceleration(h[i], v[i], vo[i], dt, A[i], J[i], margin, cap[i]) for i in range(k)])
    interior = (star > -cap) & (star < cap)
    assert interior.sum() > 30
    for scale in (1.0, 1.01):
        a = np.where(star > 0, star * scale, star / scale) if scale != 1.0 else star
        v1 = v + a * dt
        x1 = v * dt + a * dt * dt / 2
        lat = np.maximum(v1, 0.0) * dt  # the latency period at v₁ (the hold's own acceleration is ≤ its cost)
        dist, t_stop = braked(v1, a, A, J)
        left = h - x1 - dist - lat - vo * (2 * dt + t_stop) - margin
        if scale == 1.0:
            tol = 1e-6 + vo * 4e-4  # the integration's time to rest is known to its step
            assert np.all(left[interior] >= -tol[interior]), (left + tol)[interior].min()
        else:
            assert np.all(left[interior] < 0), left[interior].max()
