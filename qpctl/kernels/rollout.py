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


@njit(cache=True, error_model="numpy")
def clip_brake(tau, tau_max, prev, window):  # type: ignore[no-untyped-def]
    """τ ← clip(clip(τ, ±τ_max), τ_prev ± window) in place; no rate window while τ_prev[0] is NaN
    (nothing applied yet). The order of the clips is the oracle's."""
    rate = np.isfinite(prev[0])
    for i in range(tau.shape[0]):
        x = min(max(tau[i], -tau_max[i]), tau_max[i])
        if rate:
            x = min(max(x, prev[i] - window[i]), prev[i] + window[i])
        tau[i] = x


@njit(cache=True, error_model="numpy")
def stage(q, v, kq, ka, h, dq, qs, vs):  # type: ignore[no-untyped-def]
    """A stage's state: dq ← h·kq, qs ← q + dq (a vector space; a Lie robot integrates dq itself),
    vs ← v + h·ka (rk4_step's ``v + 0.5 * dt * k1v``: the scalar product first)."""
    for i in range(v.shape[0]):
        vs[i] = v[i] + h * ka[i]
        dq[i] = h * kq[i]
    for i in range(q.shape[0]):
        qs[i] = q[i] + dq[i]


@njit(cache=True, error_model="numpy")
def combine(k, c, out):  # type: ignore[no-untyped-def]
    """out ← c·(((k₀ + 2k₁) + 2k₂) + k₃) (rk4_step's ``dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)``)."""
    for i in range(out.shape[0]):
        out[i] = c * (((k[0, i] + 2.0 * k[1, i]) + 2.0 * k[2, i]) + k[3, i])


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
def travel(dq, rho):  # type: ignore[no-untyped-def]
    """Σᵢ ρᵢ|dqᵢ| [m]: a bound on how far any point of the links moves over a joint step dq [rad]."""
    s = 0.0
    for i in range(dq.shape[0]):
        s += rho[i] * abs(dq[i])
    return s


# --- The compiled rigid-body step (revolute one-degree-of-freedom joints) -------------------------
#
# Featherstone's RNEA and ABA in Pinocchio's conventions (spatial vectors [linear; angular], joint i's
# frame placed in its parent's by (R, t) = jointPlacement · Rot(axis, qᵢ), the body's 6×6 spatial
# inertia Pinocchio's ``Inertia.matrix()``, the base accelerating at −gravity, armature added to the
# joint's diagonal). The arrays of a model: ``parent`` (index of the parent joint, −1: the base),
# ``pl_R`` (n, 3, 3), ``pl_t`` (n, 3), ``axis`` (n, 3), ``inertia`` (n, 6, 6), ``armature`` (n,),
# ``a0`` (6,) = −gravity. Scratch: ``X`` (n, 6, 6) the motion transforms parent → joint.
#
# The results agree with Pinocchio's rnea/aba to rounding (tests/test_rollout.py: 1e-11 relative on
# random states of the planar arm and the Panda), not bit for bit: the operations are grouped
# differently.


@njit(cache=True, error_model="numpy")
def _transforms(q, pl_R, pl_t, axis, X, Rs):  # type: ignore[no-untyped-def]
    """X[i] ← the motion transform from joint i's parent frame to its own at qᵢ:
    [[Rᵀ, −Rᵀ[t]×], [0, Rᵀ]] with R = pl_R[i]·Rot(axis[i], qᵢ) (into Rs[i]), t = pl_t[i]."""
    for i in range(q.shape[0]):
        c, s = np.cos(q[i]), np.sin(q[i])
        x, y, z = axis[i, 0], axis[i, 1], axis[i, 2]
        C = 1.0 - c
        # Rodrigues: Rot = c·E + s·[a]× + (1 − c)·a aᵀ
        r00, r01, r02 = c + C * x * x, C * x * y - s * z, C * x * z + s * y
        r10, r11, r12 = C * y * x + s * z, c + C * y * y, C * y * z - s * x
        r20, r21, r22 = C * z * x - s * y, C * z * y + s * x, c + C * z * z
        P = pl_R[i]
        R = Rs[i]
        for a in range(3):
            R[a, 0] = P[a, 0] * r00 + P[a, 1] * r10 + P[a, 2] * r20
            R[a, 1] = P[a, 0] * r01 + P[a, 1] * r11 + P[a, 2] * r21
            R[a, 2] = P[a, 0] * r02 + P[a, 1] * r12 + P[a, 2] * r22
        tx, ty, tz = pl_t[i, 0], pl_t[i, 1], pl_t[i, 2]
        Xi = X[i]
        Xi[:, :] = 0.0
        for a in range(3):
            for b in range(3):
                Xi[a, b] = R[b, a]  # Rᵀ
                Xi[3 + a, 3 + b] = R[b, a]
            # row a of −Rᵀ[t]× is t × r_a (r_a: column a of R)
            ra0, ra1, ra2 = R[0, a], R[1, a], R[2, a]
            Xi[a, 3] = ty * ra2 - tz * ra1
            Xi[a, 4] = tz * ra0 - tx * ra2
            Xi[a, 5] = tx * ra1 - ty * ra0


@njit(cache=True, error_model="numpy", inline="always")
def _mv(X, m, out):  # type: ignore[no-untyped-def]
    for a in range(6):
        s = 0.0
        for b in range(6):
            s += X[a, b] * m[b]
        out[a] = s


@njit(cache=True, error_model="numpy", inline="always")
def _mtv_add(X, f, out):  # type: ignore[no-untyped-def]
    """out += Xᵀ f (a force carried to the parent)."""
    for b in range(6):
        s = 0.0
        for a in range(6):
            s += X[a, b] * f[a]
        out[b] += s


@njit(cache=True, error_model="numpy", inline="always")
def _crm(v, m, out):  # type: ignore[no-untyped-def]
    """out ← v ×ₘ m (motion cross product, [linear; angular]): (ω×u + ν×η, ω×η)."""
    out[0] = v[4] * m[2] - v[5] * m[1] + v[1] * m[5] - v[2] * m[4]
    out[1] = v[5] * m[0] - v[3] * m[2] + v[2] * m[3] - v[0] * m[5]
    out[2] = v[3] * m[1] - v[4] * m[0] + v[0] * m[4] - v[1] * m[3]
    out[3] = v[4] * m[5] - v[5] * m[4]
    out[4] = v[5] * m[3] - v[3] * m[5]
    out[5] = v[3] * m[4] - v[4] * m[3]


@njit(cache=True, error_model="numpy", inline="always")
def _crf(v, f, out):  # type: ignore[no-untyped-def]
    """out ← v ×* f (force cross product): (ω×f, ω×n + ν×f)."""
    out[0] = v[4] * f[2] - v[5] * f[1]
    out[1] = v[5] * f[0] - v[3] * f[2]
    out[2] = v[3] * f[1] - v[4] * f[0]
    out[3] = v[4] * f[5] - v[5] * f[4] + v[1] * f[2] - v[2] * f[1]
    out[4] = v[5] * f[3] - v[3] * f[5] + v[2] * f[0] - v[0] * f[2]
    out[5] = v[3] * f[4] - v[4] * f[3] + v[0] * f[1] - v[1] * f[0]


@njit(cache=True, error_model="numpy")
def rnea(q, v, a, parent, pl_R, pl_t, axis, inertia, armature, a0, X, Rs, vel, acc, frc, tmp, tau):  # type: ignore[no-untyped-def]
    """τ ← RNEA(q, q̇, q̈) (Pinocchio's ``rnea``: M q̈ + C q̇ + g, plus armature·q̈). Scratch: vel, acc,
    frc, tmp (n, 6) and (6,)-sized rows."""
    n = q.shape[0]
    _transforms(q, pl_R, pl_t, axis, X, Rs)
    w = tmp[0]
    u = tmp[1]
    for i in range(n):
        p = parent[i]
        if p < 0:
            for k in range(6):
                w[k] = 0.0
            _mv(X[i], a0, acc[i])
        else:
            _mv(X[i], vel[p], w)
            _mv(X[i], acc[p], acc[i])
        for k in range(6):
            vel[i, k] = w[k]
        for k in range(3):  # S = [0; axis]
            vel[i, 3 + k] += axis[i, k] * v[i]
            acc[i, 3 + k] += axis[i, k] * a[i]
        for k in range(6):
            u[k] = 0.0
        for k in range(3):
            u[3 + k] = axis[i, k] * v[i]
        _crm(vel[i], u, w)
        for k in range(6):
            acc[i, k] += w[k]
        _mv(inertia[i], acc[i], frc[i])
        _mv(inertia[i], vel[i], u)
        _crf(vel[i], u, w)
        for k in range(6):
            frc[i, k] += w[k]
    for i in range(n - 1, -1, -1):
        tau[i] = axis[i, 0] * frc[i, 3] + axis[i, 1] * frc[i, 4] + axis[i, 2] * frc[i, 5] + armature[i] * a[i]
        p = parent[i]
        if p >= 0:
            _mtv_add(X[i], frc[i], frc[p])


@njit(cache=True, error_model="numpy")
def aba(q, v, tau, parent, pl_R, pl_t, axis, inertia, armature, a0, X, Rs, vel, acc, c, pA, IA, U, D, uu, tmp,
        qdd):  # type: ignore[no-untyped-def]
    """q̈ ← ABA(q, q̇, τ) (Pinocchio's ``aba``). Scratch: vel, acc, c, pA, U (n, 6), IA (n, 6, 6), D, uu (n,)."""
    n = q.shape[0]
    _transforms(q, pl_R, pl_t, axis, X, Rs)
    w = tmp[0]
    s = tmp[1]
    Ia = np.empty((6, 6))
    XtI = np.empty((6, 6))
    for i in range(n):
        p = parent[i]
        if p < 0:
            for k in range(6):
                w[k] = 0.0
        else:
            _mv(X[i], vel[p], w)
        for k in range(6):
            vel[i, k] = w[k]
        for k in range(3):
            vel[i, 3 + k] += axis[i, k] * v[i]
        for k in range(6):
            s[k] = 0.0
        for k in range(3):
            s[3 + k] = axis[i, k] * v[i]
        _crm(vel[i], s, c[i])
        IA[i, :, :] = inertia[i]
        _mv(inertia[i], vel[i], s)
        _crf(vel[i], s, pA[i])
    for i in range(n - 1, -1, -1):
        for k in range(6):
            U[i, k] = IA[i, k, 3] * axis[i, 0] + IA[i, k, 4] * axis[i, 1] + IA[i, k, 5] * axis[i, 2]
        D[i] = axis[i, 0] * U[i, 3] + axis[i, 1] * U[i, 4] + axis[i, 2] * U[i, 5] + armature[i]
        uu[i] = tau[i] - (axis[i, 0] * pA[i, 3] + axis[i, 1] * pA[i, 4] + axis[i, 2] * pA[i, 5])
        p = parent[i]
        if p >= 0:
            for a in range(6):
                for b in range(6):
                    Ia[a, b] = IA[i, a, b] - U[i, a] * U[i, b] / D[i]
            _mv(Ia, c[i], w)
            for k in range(6):
                w[k] += pA[i, k] + U[i, k] * uu[i] / D[i]
            _mtv_add(X[i], w, pA[p])
            Xi = X[i]
            for a in range(6):  # XtI = Xᵀ Ia
                for b in range(6):
                    acc_ = 0.0
                    for k in range(6):
                        acc_ += Xi[k, a] * Ia[k, b]
                    XtI[a, b] = acc_
            for a in range(6):  # IA[p] += XtI X
                for b in range(6):
                    acc_ = 0.0
                    for k in range(6):
                        acc_ += XtI[a, k] * Xi[k, b]
                    IA[p, a, b] += acc_
    for i in range(n):
        p = parent[i]
        if p < 0:
            _mv(X[i], a0, acc[i])
        else:
            _mv(X[i], acc[p], acc[i])
        for k in range(6):
            acc[i, k] += c[i, k]
        qdd[i] = (uu[i] - (U[i, 0] * acc[i, 0] + U[i, 1] * acc[i, 1] + U[i, 2] * acc[i, 2] + U[i, 3] * acc[i, 3]
                           + U[i, 4] * acc[i, 4] + U[i, 5] * acc[i, 5])) / D[i]
        for k in range(3):
            acc[i, 3 + k] += axis[i, k] * qdd[i]


# --- The compiled brake rollout -------------------------------------------------------------------

#: :func:`advance`'s answers: the clearance is wanted at step k (the caller evaluates it, stores it in
#: st and calls again with have=True), the rollout failed (below stop_below or outside the limits), came
#: to rest, or ran out of steps.
NEED, FAILED, RESTED, HORIZON = 0, 1, 2, 3


@njit(cache=True, error_model="numpy")
def brake_torque(q, v, prev, gain, tau_max, window, parent, pl_R, pl_t, axis, inertia, armature, a0, X, Rs,
                 vel, acc, frc, tmp, qdd, tau):  # type: ignore[no-untyped-def]
    """τ ← clip(clip(RNEA(q, q̇, −κq̇), ±τ_max), τ_prev ± window) (the oracle's brake)."""
    for i in range(v.shape[0]):
        qdd[i] = v[i] * -gain
    rnea(q, v, qdd, parent, pl_R, pl_t, axis, inertia, armature, a0, X, Rs, vel, acc, frc, tmp, tau)
    clip_brake(tau, tau_max, prev, window)


@njit(cache=True, error_model="numpy")
def rk4(q, v, tau, dt, parent, pl_R, pl_t, axis, inertia, armature, a0, X, Rs, vel, acc, c, pA, IA, U, D, uu, tmp,
        kq, ka, qs, vs, dq, dv):  # type: ignore[no-untyped-def]
    """One RK4 step of τ held over dt, (q, q̇) in place, dq ← the step's Δq (rk4_step's operations in its
    order, ABA by :func:`aba`)."""
    n = v.shape[0]
    for i in range(n):
        kq[0, i] = v[i]
    aba(q, v, tau, parent, pl_R, pl_t, axis, inertia, armature, a0, X, Rs, vel, acc, c, pA, IA, U, D, uu, tmp, ka[0])
    for j in range(3):
        h = 0.5 * dt if j < 2 else dt
        stage(q, v, kq[j], ka[j], h, dq, qs, vs)
        for i in range(n):
            kq[j + 1, i] = vs[i]
        aba(qs, vs, tau, parent, pl_R, pl_t, axis, inertia, armature, a0, X, Rs, vel, acc, c, pA, IA, U, D, uu, tmp,
            ka[j + 1])
    combine(kq, dt / 6, dq)
    combine(ka, dt / 6, dv)
    for i in range(n):
        q[i] += dq[i]
        v[i] += dv[i]


@njit(cache=True, error_model="numpy")
def advance(q, v, prev, k, steps, have, st, gain, dt, lazy, level, stop_below, rest_speed, rest_time, q_min, q_max,
            rho, obstacle_speed, trace, tau_max, window, parent, pl_R, pl_t, axis, inertia, armature, a0, X, Rs, vel,
            acc, frc, c, pA, IA, U, D, uu, tmp, kq, ka, qs, vs, dq, dv, qdd, tau):  # type: ignore[no-untyped-def]
    """The brake rollout's loop (:meth:`qpctl.safety.rollout.BrakeRollout.run`) from step k until it
    needs a clearance (NEED: not lazy, or the bound last − drift no longer above ``level``), fails,
    rests or reaches ``steps``; returns (answer, step). st = [worst, still, last, drift] carries the
    loop's scalars across calls; ``have``: the clearance of step k was just stored in st. States are
    written into ``trace[k]`` when it has rows (a test's record)."""
    record = trace.shape[0] > 0
    while k < steps:
        if not have:
            if lazy and st[2] - st[3] > level:
                st[0] = min(st[0], st[2] - st[3])
            else:
                return NEED, k
        have = False
        code = state_code(q, v, q_min, q_max, rest_speed)
        if st[0] < stop_below or code == OUTSIDE:
            return FAILED, k
        st[1] = st[1] + dt if code == AT_REST else 0.0
        if st[1] >= rest_time:
            return RESTED, k
        brake_torque(q, v, prev, gain, tau_max, window, parent, pl_R, pl_t, axis, inertia, armature, a0, X, Rs, vel,
                     acc, frc, tmp, qdd, tau)
        for i in range(v.shape[0]):
            prev[i] = tau[i]
        rk4(q, v, tau, dt, parent, pl_R, pl_t, axis, inertia, armature, a0, X, Rs, vel, acc, c, pA, IA, U, D, uu, tmp,
            kq, ka, qs, vs, dq, dv)
        if lazy:
            st[3] += travel(dq, rho) + obstacle_speed * dt
        k += 1
        if record and k < trace.shape[0]:
            trace[k, :] = q
    return HORIZON, steps


@njit(cache=True, error_model="numpy")
def advance_packed(q, v, prev, k, steps, have, st, par, L, parent, pl_R, pl_t, axis, inertia, armature, a0, S66, Rs,
                   S6, tmp, Sn, K4, trace):  # type: ignore[no-untyped-def]
    """:func:`advance` with its arguments packed (a call from Python costs per argument): par =
    [gain, dt, lazy, level, stop_below, rest_speed, rest_time, obstacle_speed], L = [q_min, q_max, ρ,
    τ_max, window], S66 = [X, IA], S6 = [vel, acc, frc, c, pA, U], Sn = [D, uu, qs, vs, dq, dv, q̈, τ],
    K4 = [kq, ka]."""
    return advance(q, v, prev, k, steps, have, st, par[0], par[1], par[2] != 0.0, par[3], par[4], par[5], par[6],
                   L[0], L[1], L[2], par[7], trace, L[3], L[4], parent, pl_R, pl_t, axis, inertia, armature, a0,
                   S66[0], Rs, S6[0], S6[1], S6[2], S6[3], S6[4], S66[1], S6[5], Sn[0], Sn[1], tmp, K4[0], K4[1],
                   Sn[2], Sn[3], Sn[4], Sn[5], Sn[6], Sn[7])
