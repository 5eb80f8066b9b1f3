"""The arithmetic of a settled retreat's walk (:mod:`qpctl.safety.walk`), compiled: the steering in
closed form, the torque samples' test and the walk's clearance loop —
brake_rollout.cpp's ``steer_state``, ``qpb_walk_plan``'s sample test and
``qpb_walk_clear`` in the same order of operations, so that the Python path and the native one give
the same walks bit for bit. No rigid-body quantity is computed here (Pinocchio's RNEA is called from
Python between these).
"""

from __future__ import annotations

import math

from numba import njit

# the walk's io block (qpctl.safety.walk.W_*; brake_rollout.cpp's W_* order)
(W_K, W_T0, W_DT, W_UNTIL, W_OMEGA, W_GAIN, W_BETA, W_EVERY, W_STRAY, W_STEPS, W_NSW, W_DEV, W_RETRY, W_J,
 W_LAST, W_DRIFT, W_WORST, W_EVALUATED, W_LEVEL, W_LAZY, W_MOVE, W_PROG, W_SWITCH_STRAY, W_SIZE) = range(24)
#: :func:`walk_clear`'s answers (NEED_CLEARANCE is the rollout's 0)
NEED_CLEARANCE, WALKED, REFUSED = 0, 1, 2


@njit(cache=True)
def steer_state(q0, v0, target, w, s, q, v):  # type: ignore[no-untyped-def]
    """The unclipped steering s [s] after (q₀, q̇₀) into (q, q̇): q = q* + (e₀ + c·s)e^{−ωs},
    q̇ = (q̇₀ − ω·c·s)e^{−ωs}, e₀ = q₀ − q*, c = q̇₀ + ω·e₀."""
    x = math.exp(-w * s)
    for i in range(q0.shape[0]):
        e0 = q0[i] - target[i]
        c = v0[i] + w * e0
        q[i] = target[i] + (e0 + c * s) * x
        v[i] = (v0[i] - w * c * s) * x


@njit(cache=True)
def sample_ok(tau, before, tau_max, window, beta, span):  # type: ignore[no-untyped-def]
    """True if a sampled steering torque τ [N·m] is within ``beta`` of τ_max and its change from the
    sample ``before`` within ``span`` (β × the steps between) of the rate window."""
    for i in range(tau.shape[0]):
        if not (abs(tau[i]) <= beta * tau_max[i]) or not (abs(tau[i] - before[i]) <= span * window[i]):
            return False
    return True


@njit(cache=True)
def walk_clear(q0, v0, target, q_min, q_max, rho, T, wq, wv, wprev, wio):  # type: ignore[no-untyped-def]
    """brake_rollout.cpp's ``qpb_walk_clear`` (its comment; :mod:`qpctl.safety.walk`): the walk's
    clearance from step wio[W_J] on, returning NEED_CLEARANCE, WALKED or REFUSED."""
    n = q0.shape[0]
    nsw = int(wio[W_NSW])
    dt, w, level, move = wio[W_DT], wio[W_OMEGA], wio[W_LEVEL], wio[W_MOVE]
    stray = wio[W_STRAY]
    lazy = wio[W_LAZY] != 0.0
    last, drift, worst, prog = wio[W_LAST], wio[W_DRIFT], wio[W_WORST], wio[W_PROG]
    evaluated = wio[W_EVALUATED] != 0.0
    j = int(wio[W_J]) + (0 if evaluated else 1)
    answer = REFUSED
    while j <= nsw:
        bound = last
        if not evaluated:
            steer_state(q0, v0, target, w, float(j) * dt, wq, wv)
            travel = 0.0
            for i in range(n):
                d = abs(wq[i] - wprev[i])
                T[i] += d
                travel += rho[i] * d
                wprev[i] = wq[i]
            prog += travel
            drift += travel + move
            if j == nsw:
                dev = 0.0
                for i in range(n):
                    T[i] += abs(wv[i]) / wio[W_GAIN]
                    dev += rho[i] * T[i]
                wio[W_DEV] = wio[W_SWITCH_STRAY] * dev
                answer = WALKED
                break
            if not (lazy and last - drift - stray * prog > level):
                answer = NEED_CLEARANCE
                break
            bound = last - drift
        evaluated = False
        dev = stray * prog
        if not (bound - dev > level):
            answer = REFUSED
            break
        worst = min(worst, bound - dev)
        turn = 0.0  # every joint's travel so far [rad]: the dynamics couple the joints' strays
        for i in range(n):
            turn += T[i]
        d = stray * turn
        inside = True
        for i in range(n):
            inside = inside and wq[i] - d >= q_min[i] and wq[i] + d <= q_max[i]
        if not inside:
            answer = REFUSED
            break
        j += 1
    wio[W_J] = float(j)
    wio[W_LAST], wio[W_DRIFT], wio[W_WORST], wio[W_PROG] = last, drift, worst, prog
    wio[W_EVALUATED] = 1.0 if evaluated else 0.0
    if answer == REFUSED:  # tried again halfway to where it was refused (the stray grows from a walk's start)
        wio[W_RETRY] = wio[W_K] + max(math.floor(0.5 * float(j)), wio[W_EVERY])
    return answer
