"""Every compiled kernel of the tick held against a slow, obviously-correct reference (DESIGN.md §5).

References (none of them goes through the kernel it checks):

* ``qpctl.kernels.small`` — numpy's Cholesky, triangular solves and SVD; :func:`qpctl.linalg.weighted_pinv`
  (numpy's LAPACK SVD with the same variable damping) and ``np.linalg.pinv``.
* ``qpctl.kernels.geometry`` — python-fcl on the same shapes (capsules placed by a rotation written
  here, not :func:`quaternion_z_to`), and a brute-force segment–segment distance: a ternary search
  over the first segment's parameter of the (convex) distance to the second segment, each point's
  distance to a segment by clamped projection; plus a dense grid of both parameters as a one-sided check.
* the Workspace's state — Pinocchio's own per-frame functions on a separate model copy with probe
  frames (crba, nonLinearEffects, getFrameJacobian, getFrameClassicalAcceleration), and the pair
  list by enumerating every (link, obstacle) pair with python-fcl (and the brute-force distance).
* the laws and the QP assembly — :mod:`qpctl.law`, the baselines' numpy ``control`` and
  :class:`qpctl.formulation.Formulation` (the Python path of the same controllers).

Tolerances (and why):

* small dense algebra: 1e-12 relative (backward-stable algorithms on well-conditioned matrices);
  the damped pseudo-inverse 1e-11 relative plus its own conditioning where it is damped: d/dσ of
  σ/(σ² + λ²) is 1/λ² at σ → 0, so a rounding-level difference ε·σ_max between two SVDs' σ_min moves
  the result by ~ε/(eps²·σ_max) (the bound below allows 100× that);
* distances between spheres and capsules: 1e-9 m against python-fcl's closed forms (they agree to
  ~1e-15 in practice) and against the brute force; witness points 1e-6 m; penetrating pairs against
  python-fcl's signed (GJK/EPA) query within 2e-3 m, its own accuracy;
* boxes and cylinders (python-fcl's GJK on both sides, differently posed capsules): 1e-5 m (box) and
  1e-3 m (cylinder: the same query, posed two ways, differs by up to 2e-4 m) when separated;
* rigid-body terms: 1e-12 relative to each quantity's scale (the same algebra in another order);
* law torques 1e-9 relative; QP data 1e-9 relative entry-wise (with an absolute floor of 1e-14 of
  the array's largest entry for entries that are themselves cancellations); QP torques of the
  compiled and the Python path 1e-8 relative (two solves of the same problem).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import textwrap
from collections.abc import Sequence

import fcl
import numpy as np
import pinocchio as pin
import pytest
from solid_reference import fcl_segment, frame_z_to, minimised_distance

from baselines import HsuController, PaperController
from qpctl import LawGains, Obstacle, Scenario, WaypointPath, panda, planar_arm
from qpctl.controllers.qp import QPConfig, QPController
from qpctl.kernels import codes
from qpctl.kernels import geometry as G
from qpctl.kernels import small as S
from qpctl.law import law_terms
from qpctl.linalg import weighted_pinv
from qpctl.robot.model import RobotModel
from qpctl.tasks import AccelerationTask, DampingTask, EndEffectorTask, PostureTask
from qpctl.tick import GRID_MIN_OBSTACLES, Workspace, WorldClearance, bind_pinocchio, rigid_pass

SEED = 20240611
EPA_TOL = 2e-3  # python-fcl's signed distance of penetrating shapes (libccd EPA) [m]
GJK_TOL = {"box": 1e-5, "cylinder": 1e-3}  # python-fcl's GJK distance of a capsule to these shapes [m]

_UNSIGNED = fcl.DistanceRequest(enable_nearest_points=True, enable_signed_distance=False)
_SIGNED = fcl.DistanceRequest(enable_nearest_points=True, enable_signed_distance=True)


# ---------------------------------------------------------------------------------------------------
# References: python-fcl shapes, brute-force segment distances, Pinocchio per-frame quantities
# ---------------------------------------------------------------------------------------------------
def obstacle_centre(o: Obstacle, t: float) -> np.ndarray:
    """p(t) = p₀ + v t + A sin(2π f t), written out here."""
    return o.position + o.velocity * t + o.amplitude * math.sin(2.0 * math.pi * o.frequency * t)


def fcl_obstacle(o: Obstacle, t: float) -> fcl.CollisionObject:
    c = obstacle_centre(o, t)
    if o.shape == "sphere":
        return fcl.CollisionObject(fcl.Sphere(o.radius), fcl.Transform(c))
    if o.shape == "box":  # the tests' boxes keep the default axis (z): no rotation
        assert np.array_equal(o.axis, [0.0, 0.0, 1.0])
        return fcl.CollisionObject(fcl.Box(*o.size), fcl.Transform(c))
    geom = fcl.Capsule(o.radius, o.length) if o.shape == "capsule" else fcl.Cylinder(o.radius, o.length)
    return fcl.CollisionObject(geom, fcl.Transform(frame_z_to(o.axis), c))


def obstacle_axis(o: Obstacle, t: float) -> tuple[np.ndarray, np.ndarray]:
    """End points of a capsule obstacle's axis (both the centre for a sphere)."""
    c = obstacle_centre(o, t)
    half = 0.5 * o.length * o.axis / np.linalg.norm(o.axis) if o.shape == "capsule" else np.zeros(3)
    return c - half, c + half


def fcl_distance(o1: fcl.CollisionObject, o2: fcl.CollisionObject) -> tuple[float, np.ndarray, np.ndarray]:
    """(distance, nearest point on o1, on o2): the plain query when apart, the signed one otherwise."""
    res = fcl.DistanceResult()
    d = fcl.distance(o1, o2, _UNSIGNED, res)
    if d <= 0.0:
        res = fcl.DistanceResult()
        d = fcl.distance(o1, o2, _SIGNED, res)
    return float(d), np.array(res.nearest_points[0]), np.array(res.nearest_points[1])


def _point_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance, parameter) of the points p (N, 3) to the segments a–b (N, 3): clamped projection."""
    d = b - a
    dd = np.einsum("ij,ij->i", d, d)
    t = np.clip(np.einsum("ij,ij->i", p - a, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
    t = np.where(dd > 0, t, 0.0)
    return np.linalg.norm(p - a - t[:, None] * d, axis=1), t


def brute_segment_distance(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray,
                           q2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(distance, s, t) of N segment pairs ((N, 3) each), by brute force: g(s) = dist(p1 + s(q1 − p1),
    segment 2) is convex, so a ternary search over s (200 steps: the bracket shrinks by (2/3)²⁰⁰)
    finds its minimum; t is the clamped projection of that point."""
    p1, q1, p2, q2 = (np.atleast_2d(np.asarray(x, float)) for x in (p1, q1, p2, q2))

    def g(s: np.ndarray) -> np.ndarray:
        return _point_segment(p1 + s[:, None] * (q1 - p1), p2, q2)[0]

    lo, hi = np.zeros(len(p1)), np.ones(len(p1))
    for _ in range(200):
        m1, m2 = lo + (hi - lo) / 3, hi - (hi - lo) / 3
        left = g(m1) < g(m2)
        hi = np.where(left, m2, hi)
        lo = np.where(left, lo, m1)
    s = 0.5 * (lo + hi)
    # the end points too (a flat g on parallel segments, or a minimum at s = 0 or 1 exactly)
    best, best_s = g(s), s
    for end in (np.zeros_like(s), np.ones_like(s)):
        ge = g(end)
        better = ge < best
        best, best_s = np.where(better, ge, best), np.where(better, end, best_s)
    dist, t = _point_segment(p1 + best_s[:, None] * (q1 - p1), p2, q2)
    return dist, best_s, t


def grid_segment_distance(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray, k: int = 101) -> float:
    """min over a k×k grid of both parameters (an upper bound on the true distance)."""
    s = np.linspace(0.0, 1.0, k)
    P = p1 + s[:, None] * (q1 - p1)
    Q = p2 + s[:, None] * (q2 - p2)
    return float(np.linalg.norm(P[:, None, :] - Q[None, :, :], axis=2).min())


def capsule_pair(a: np.ndarray, b: np.ndarray, rl: float, c0: np.ndarray, c1: np.ndarray,
                 ro: float) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """The kernel, with fresh output arrays: (d, normal, p_link, p_obs)."""
    n, pl, po = np.full(3, np.nan), np.full(3, np.nan), np.full(3, np.nan)
    d = G.capsule_pair(*(np.ascontiguousarray(x, dtype=float) for x in (a, b)), float(rl),
                       *(np.ascontiguousarray(x, dtype=float) for x in (c0, c1)), float(ro), n, pl, po)
    return float(d), n, pl, po


def on_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Distance of p from the segment a–b."""
    return float(_point_segment(p[None], a[None], b[None])[0][0])


class PinReference:
    """Pinocchio's own per-frame quantities at (q, v) on a copy of the model with one probe frame per
    joint (moved onto any body point to read its Jacobian and classical acceleration)."""

    def __init__(self, robot: RobotModel) -> None:
        self.robot = robot
        self.model = pin.Model(robot.model)
        self.probe = {j: self.model.addFrame(pin.Frame(f"probe{j}", j, 0, pin.SE3.Identity(),
                                                       pin.FrameType.OP_FRAME))
                      for j in range(1, self.model.njoints)}
        self.data = self.model.createData()

    def at(self, q: np.ndarray, v: np.ndarray) -> None:
        m, d = self.model, self.data
        pin.forwardKinematics(m, d, q, v, np.zeros(m.nv))  # q̈ = 0: accelerations are the drifts
        pin.computeJointJacobians(m, d, q)
        pin.updateFramePlacements(m, d)
        M = pin.crba(m, d, q)
        self.M = np.triu(M) + np.triu(M, 1).T
        self.N = pin.nonLinearEffects(m, d, q, v).copy()

    def task(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x, J, J̇q̇ of the task point on the task axes."""
        fid, axes = self.robot.ee_frame_id, list(self.robot.task_axes)
        x = self.data.oMf[fid].translation[axes]
        J = pin.getFrameJacobian(self.model, self.data, fid, pin.LOCAL_WORLD_ALIGNED)[:3][axes]
        a = pin.getFrameClassicalAcceleration(self.model, self.data, fid, pin.LOCAL_WORLD_ALIGNED).linear[axes]
        return x.copy(), J.copy(), a.copy()

    def point(self, joint: int, p_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(3, n) Jacobian and classical acceleration at q̈ = 0 of the point of joint ``joint``'s body
        that is at p_world now."""
        fid = self.probe[joint]
        self.model.frames[fid].placement = pin.SE3(np.eye(3), self.data.oMi[joint].actInv(np.asarray(p_world)))
        J = pin.getFrameJacobian(self.model, self.data, fid, pin.LOCAL_WORLD_ALIGNED)[:3]
        a = pin.getFrameClassicalAcceleration(self.model, self.data, fid, pin.LOCAL_WORLD_ALIGNED).linear
        return J.copy(), a.copy()

    def segment(self, joint: int, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
        return np.array([self.data.oMi[joint].act(np.asarray(p0, float)),
                         self.data.oMi[joint].act(np.asarray(p1, float))])


def sample_states(robot: RobotModel, rng: np.random.Generator, k: int, v_scale: float = 1.5
                  ) -> list[tuple[np.ndarray, np.ndarray, float]]:
    lo = np.where(np.isfinite(robot.q_min), robot.q_min, -np.pi)
    hi = np.where(np.isfinite(robot.q_max), robot.q_max, np.pi)
    margin = 0.05 * (hi - lo)
    return [(rng.uniform(lo + margin, hi - margin), rng.uniform(-v_scale, v_scale, robot.nv), float(rng.uniform(0, 3)))
            for _ in range(k)]


def assert_close(got: np.ndarray, want: np.ndarray, rtol: float, what: str) -> None:
    """|got − want| ≤ rtol · max(‖want‖∞, 1e-300), with the same infinities."""
    got, want = np.asarray(got, float), np.asarray(want, float)
    assert got.shape == want.shape, f"{what}: shape {got.shape} != {want.shape}"
    assert np.array_equal(np.isposinf(got), np.isposinf(want)) and np.array_equal(np.isneginf(got),
                                                                                     np.isneginf(want)), \
        f"{what}: infinities differ"
    fin = np.isfinite(want)
    assert np.isfinite(got[fin]).all(), f"{what}: non-finite entries"
    scale = float(np.max(np.abs(want[fin]), initial=0.0))
    err = float(np.max(np.abs(got[fin] - want[fin]), initial=0.0))
    assert err <= rtol * max(scale, 1e-300), f"{what}: |Δ| = {err:.3e} > {rtol:.0e} · {scale:.3e}"


# ---------------------------------------------------------------------------------------------------
# 1. qpctl.kernels.small
# ---------------------------------------------------------------------------------------------------
def random_spd(rng: np.random.Generator, n: int) -> np.ndarray:
    B = rng.standard_normal((n, n))
    return B @ B.T + n * np.eye(n)


@pytest.mark.parametrize("n", [1, 2, 3, 7, 9])
def test_cholesky_and_triangular_solves_equal_numpy(n):
    rng = np.random.default_rng(SEED + n)
    for _ in range(10):
        A = random_spd(rng, n)
        L = np.full((n, n), 3.0)  # garbage above the diagonal: the kernel must zero it
        assert S.cholesky(A, L)
        np.testing.assert_allclose(L, np.linalg.cholesky(A), rtol=0, atol=1e-12 * np.abs(L).max())
        assert np.array_equal(np.triu(L, 1), np.zeros((n, n)))
        for X0 in (rng.standard_normal(n), rng.standard_normal((n, 4))):
            scale = np.abs(np.linalg.solve(A, X0)).max()
            X = X0.copy()
            S.solve_lower(L, X)
            np.testing.assert_allclose(X, np.linalg.solve(np.tril(L), X0), rtol=0, atol=1e-12 * max(1, np.abs(X).max()))
            X = X0.copy()
            S.solve_lower_t(L, X)
            np.testing.assert_allclose(X, np.linalg.solve(np.tril(L).T, X0), rtol=0,
                                       atol=1e-12 * max(1, np.abs(X).max()))
            X = X0.copy()
            S.chol_solve(L, X)
            np.testing.assert_allclose(X, np.linalg.solve(A, X0), rtol=0, atol=1e-12 * scale)
    # not positive definite: refused (an indefinite and a singular matrix)
    A = random_spd(rng, n)
    A[n - 1, n - 1] = -1.0 - np.abs(A).sum()
    assert not S.cholesky(A, np.zeros((n, n)))
    assert not S.cholesky(np.zeros((n, n)), np.zeros((n, n)))


def _orthonormal(rng: np.random.Generator, n: int, m: int) -> np.ndarray:
    Q, _ = np.linalg.qr(rng.standard_normal((n, m)))
    return Q


PINV_CASES = ["full", "below", "above", "far_below", "duplicate_row", "zero_row", "zero"]


def _pinv_case(rng: np.random.Generator, case: str, m: int, n: int, eps: float) -> np.ndarray:
    """An m × n matrix of the PINV_CASES kind ``case`` (see the test below)."""
    s = np.sort(rng.uniform(0.5, 3.0, m))[::-1] * 10 ** rng.uniform(-2, 2)
    if m > 1:
        s[-1] = {"below": 0.99 * eps, "above": 1.01 * eps, "far_below": 1e-6}.get(case, s[-1] / s[0]) * s[0]
    A = (_orthonormal(rng, m, m) * s) @ _orthonormal(rng, n, m).T
    if case == "duplicate_row" and m > 1:
        A[-1] = A[0] * rng.uniform(0.5, 2.0)
    if case == "zero_row" and m > 1:
        A[-1] = 0.0
    if case == "zero":
        A[:] = 0.0
    return A


def _pinv_cases(rng: np.random.Generator, case: str, eps: float):  # type: ignore[no-untyped-def]
    """(m, n, A): three matrices of the kind ``case`` for each m = 1..6 rows and n = m..9 columns."""
    for m in range(1, 7):
        for n in range(m, 10):
            for _ in range(3):
                yield m, n, _pinv_case(rng, case, m, n, eps)


@pytest.mark.parametrize("case", PINV_CASES)
def test_pinv_t_equals_numpy_svd_damped_pseudo_inverse(case):
    """pinv_t against weighted_pinv (numpy's LAPACK SVD, same damping) for m = 1..6 rows, n = m..9
    columns: same matrix, same singular flag, same σ_min/σ_max. Cases: full rank; σ_min/σ_max just
    below (0.99 eps) and above (1.01 eps) the damping threshold; far below (1e-3 eps); rank-deficient
    by a duplicated (scaled) row and by a zero row; the zero matrix."""
    rng = np.random.default_rng(SEED + PINV_CASES.index(case))
    eps = 1e-3
    checked = 0
    for m, n, A in _pinv_cases(rng, case, eps):
        B = np.ascontiguousarray(A.T)
        V, out = np.full((m, m), 5.0), np.full((n, m), 7.0)
        singular, ratio = S.pinv_t(B, eps, V, out)
        ref = weighted_pinv(A, None, eps=eps)
        assert singular == ref.singular, f"m={m} n={n}: singular {singular} != {ref.singular}"
        assert abs(ratio - ref.sigma_ratio) <= 1e-12, f"m={m} n={n}: ratio {ratio} != {ref.sigma_ratio}"
        if case == "zero":
            assert singular and ratio == 0.0 and np.array_equal(out, np.zeros((n, m)))
            checked += 1
            continue
        smax = np.linalg.svd(A, compute_uv=False)[0]
        tol = 1e-11 * np.abs(ref.matrix).max()
        if ref.singular:  # the damped inverse's own sensitivity to σ_min (module docstring)
            tol += 100 * np.finfo(float).eps / (eps**2 * smax)
        err = np.abs(out - ref.matrix).max()
        assert err <= tol, f"m={m} n={n}: |Δ| = {err:.3e} > {tol:.3e}"
        if case in ("full", "above"):  # undamped: the Moore–Penrose inverse itself
            assert not singular
            np.testing.assert_allclose(out, np.linalg.pinv(A), rtol=0, atol=1e-11 * np.abs(out).max())
        if case in ("below", "far_below", "duplicate_row", "zero_row") and m > 1:
            assert singular
        checked += 1
    assert checked == 3 * sum(10 - m for m in range(1, 7))


def test_gram_lower_equals_numpy():
    """gram_lower (the reference velocity's and W_b's normal matrices) against numpy's A Aᵀ over the
    first k columns, lower triangle, to rounding: shapes from 1×0 to 9×40,
    k below the array's width (the rest of A is garbage it must not read), the upper triangle left as
    it was, each entry bit for bit its products summed in column order (the same rounding in every
    process), and a NaN in A reaching H (no fastmath flag may assume finite values)."""
    rng = np.random.default_rng(SEED + 77)
    for n in (1, 3, 7, 9):
        for k in (0, 1, 5, 21, 33, 40):
            A = rng.standard_normal((n, k + 7)) * 10.0 ** rng.uniform(-3, 3)
            H = np.full((n, n), 5.0)
            S.gram_lower(A, k, H)
            want = A[:, :k] @ A[:, :k].T
            low = np.tril_indices(n)
            np.testing.assert_allclose(H[low], want[low], rtol=1e-13, atol=1e-13 * max(np.abs(want).max(), 1e-300))
            assert np.all(H[np.triu_indices(n, 1)] == 5.0)
    A = rng.standard_normal((3, 4))  # H larger than A A^T (the QP's cost): only its n x n block written
    H = np.full((5, 5), 5.0)
    S.gram_lower(A, 4, H)
    np.testing.assert_allclose(H[np.tril_indices(3)], (A @ A.T)[np.tril_indices(3)], rtol=1e-13)
    assert np.all(H[3:, :] == 5.0) and np.all(H[:, 3:] == 5.0)
    for n in (1, 2, 5, 8):  # bit for bit the sum of each entry's products in column order, one at a time
        A = rng.standard_normal((n, 13)) * 10.0 ** rng.uniform(-3, 3, (n, 1))
        H = np.zeros((n, n))
        S.gram_lower(A, 11, H)
        for i in range(n):
            for j in range(i + 1):
                want_ij = 0.0
                for c in range(11):
                    want_ij += float(A[i, c]) * float(A[j, c])
                assert H[i, j] == want_ij, (n, i, j)
    A = rng.standard_normal((4, 6))
    A[2, 3] = np.nan
    H = np.zeros((4, 4))
    S.gram_lower(A, 6, H)
    assert np.isnan(H[2, :3]).all() and np.isnan(H[3, 2]) and np.isnan(H[2, 2]) and np.isfinite(H[1, 0])


def _normal_equations_undamped(A: np.ndarray, eps: float) -> bool:
    """The normal equations' fast path's condition, from numpy: G = A Aᵀ positive definite and the
    bound √(1/(tr G · tr G⁻¹)) at least eps."""
    G = A @ A.T
    lam = np.linalg.eigvalsh(G)
    return bool(lam[0] > 1e-12 * max(lam[-1], 1e-300)
                and np.sqrt(1 / (np.trace(G) * np.trace(np.linalg.inv(G)))) >= eps)


@pytest.mark.parametrize("case", PINV_CASES)
def test_pinv_t_normal_equals_pinv_t(case):
    """pinv_t_normal (the normal equations where the bound certainly says undamped) against pinv_t on
    the same matrices as above: the same singular flag, the same inverse to 1e-9 relative (cond ≤
    1/eps: the normal equations lose at most cond² · 1e-16); the fast path taken on the full-rank
    cases with σ_min/σ_max ≥ m·eps, pinv_t's own result (B overwritten) near and below the threshold."""
    rng = np.random.default_rng(SEED + 40 + PINV_CASES.index(case))
    eps = 1e-3
    fast = 0
    for m, n, A in _pinv_cases(rng, case, eps):
        B1, B2 = np.ascontiguousarray(A.T), np.ascontiguousarray(A.T)
        o1, o2 = np.full((n, m), 7.0), np.full((n, m), 7.0)
        s1, _ = S.pinv_t(B1, eps, np.zeros((m, m)), o1)
        s2, bound = S.pinv_t_normal(B2, eps, np.zeros((m, m)), o2, np.zeros((m, m + 2)))
        assert s1 == s2, f"m={m} n={n}: singular {s2} != {s1}"
        np.testing.assert_allclose(o2, o1, rtol=0, atol=1e-9 * max(np.abs(o1).max(), 1e-300))
        took_fast = _normal_equations_undamped(A, eps)
        fast += took_fast
        if took_fast:  # the bound: a lower bound on σ_min/σ_max, at least eps; B kept
            sv = np.linalg.svd(A, compute_uv=False)
            assert eps <= bound <= sv[-1] / sv[0] * (1 + 1e-9) and np.array_equal(B2, A.T)
    if case == "full":
        assert fast == 3 * sum(10 - m for m in range(1, 7))
    if case in ("below", "far_below"):
        assert fast == 3 * 9  # m = 1 only (a single row is never singular unless zero)
    if case == "zero":
        assert fast == 0


@pytest.mark.parametrize("case", PINV_CASES)
def test_pinv_t_apply_equals_numpy_pseudo_inverse_times_a_vector(case):
    """pinv_t_apply (A⁺ s as one right-hand side of the normal equations) against numpy's SVD
    pseudo-inverse times s, where numpy's condition (σ_min/σ_max, and the bound from numpy's
    eigenvalues and inverse) says the normal equations are certainly undamped; elsewhere it declines
    (False) and leaves z and B as they were, so that the caller forms the damped A⁺."""
    rng = np.random.default_rng(SEED + 50 + PINV_CASES.index(case))
    eps = 1e-3
    applied = 0
    for m, n, A in _pinv_cases(rng, case, eps):
        s = rng.standard_normal(m)
        B = np.ascontiguousarray(A.T)
        z = np.full(n, 7.0)
        ok = S.pinv_t_apply(B, eps, np.zeros((m, m)), np.zeros((m, m + 2)), s, z)
        expect = _normal_equations_undamped(A, eps)
        assert ok == expect, f"m={m} n={n}"
        assert np.array_equal(B, A.T)
        if ok:
            applied += 1
            ref = np.linalg.pinv(A) @ s
            np.testing.assert_allclose(z, ref, rtol=0, atol=1e-9 * max(np.abs(ref).max(), 1e-300))
        else:
            assert (z == 7.0).all()
    if case == "full":
        assert applied == 3 * sum(10 - m for m in range(1, 7))
    if case in ("below", "far_below"):
        assert applied == 3 * 9
    if case == "zero":
        assert applied == 0


# ---------------------------------------------------------------------------------------------------
# 2. qpctl.kernels.geometry
# ---------------------------------------------------------------------------------------------------
def random_pair(rng: np.random.Generator, sphere: bool, radius: tuple[float, float]
                ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray, float]:
    a, b, c0 = rng.uniform(-1, 1, (3, 3))
    c1 = c0.copy() if sphere else c0 + rng.uniform(-1, 1, 3)
    rl, ro = rng.uniform(*radius, 2)
    return a, b, float(rl), c0, c1, float(ro)


@pytest.mark.parametrize("sphere", [True, False], ids=["capsule-sphere", "capsule-capsule"])
def test_capsule_pair_separated_matches_fcl(sphere):
    """300 random separated pairs: distance to 1e-9 m (python-fcl's closed forms and the brute force),
    witness points to 1e-6 m (python-fcl's nearest points), the normal the unit vector from the
    obstacle's witness to the link's, p_link − p_obs = d·n."""
    rng = np.random.default_rng(SEED + sphere)
    rows = []
    while len(rows) < 300:
        a, b, rl, c0, c1, ro = random_pair(rng, sphere, (0.01, 0.2))
        d_ref, p1, p2 = fcl_distance(fcl_segment(a, b, rl), fcl_segment(c0, c1, ro))
        if d_ref <= 1e-6:
            continue
        d, n, pl, po = capsule_pair(a, b, rl, c0, c1, ro)
        assert abs(d - d_ref) <= 1e-9, (a, b, rl, c0, c1, ro, d, d_ref)
        assert np.linalg.norm(pl - p1) <= 1e-6 and np.linalg.norm(po - p2) <= 1e-6, (a, b, c0, c1, pl, p1, po, p2)
        assert abs(np.linalg.norm(n) - 1.0) <= 1e-12
        np.testing.assert_allclose(n, (pl - po) / np.linalg.norm(pl - po), atol=1e-9)
        np.testing.assert_allclose(pl - po, d * n, atol=1e-12)
        rows.append((a, b, c0, c1, rl + ro, d))
    a, b, c0, c1, radii, d = (np.array(x) for x in zip(*rows))
    bf, _, _ = brute_segment_distance(a, b, c0, c1)
    np.testing.assert_allclose(d, bf - radii, rtol=0, atol=1e-9)


@pytest.mark.parametrize("sphere", [True, False], ids=["capsule-sphere", "capsule-capsule"])
def test_capsule_pair_penetrating_matches_fcl_signed_and_brute_force(sphere):
    """150 random penetrating pairs: the signed distance within python-fcl's EPA accuracy (2e-3 m) and
    to 1e-9 m of the brute force (the axes' distance less both radii, exact for capsules); the axis
    points P = p_link + r_link n, Q = p_obs − r_obs n lie on their segments and are a closest pair."""
    rng = np.random.default_rng(SEED + 10 + sphere)
    rows = []
    while len(rows) < 150:
        a, b, rl, c0, c1, ro = random_pair(rng, sphere, (0.2, 0.6))
        d, n, pl, po = capsule_pair(a, b, rl, c0, c1, ro)
        if d >= -1e-3:
            continue
        # python-fcl's EPA stalls for a sphere centred on (within ~0.1 mm of) the link's axis end
        if sphere and min(np.linalg.norm(c0 - a), np.linalg.norm(c0 - b)) < 1e-2:
            continue
        d_fcl, _, _ = fcl_distance(fcl_segment(a, b, rl), fcl_segment(c0, c1, ro))
        assert abs(d - d_fcl) <= EPA_TOL, (a, b, rl, c0, c1, ro, d, d_fcl)
        assert abs(np.linalg.norm(n) - 1.0) <= 1e-12
        np.testing.assert_allclose(pl - po, d * n, atol=1e-12)
        P, Q = pl + rl * n, po - ro * n
        assert on_segment(P, a, b) <= 1e-12 and on_segment(Q, c0, c1) <= 1e-12
        rows.append((a, b, c0, c1, rl + ro, d, np.linalg.norm(P - Q)))
    a, b, c0, c1, radii, d, pq = (np.array(x) for x in zip(*rows))
    bf, _, _ = brute_segment_distance(a, b, c0, c1)
    np.testing.assert_allclose(d, bf - radii, rtol=0, atol=1e-9)
    np.testing.assert_allclose(pq, bf, rtol=0, atol=1e-9)


def test_capsule_pair_parallel_segments():
    """Exactly parallel (and anti-parallel) axes, overlapping, partly overlapping, end to end and
    apart along the axis: the distance equals the brute force's and python-fcl's (when apart) to
    1e-9 m; the witness points are a valid closest pair (axis points on their segments, |P − Q| the
    segments' distance, n along P − Q)."""
    rng = np.random.default_rng(SEED + 20)
    rows = []
    for k in range(120):
        u = rng.standard_normal(3)
        u /= np.linalg.norm(u)
        perp = np.cross(u, rng.standard_normal(3))
        perp /= np.linalg.norm(perp)
        a = rng.uniform(-1, 1, 3)
        length = rng.uniform(0.2, 1.0)
        b = a + length * u
        gap = rng.choice([0.0, 0.05, 0.3, 1.0])
        shift = rng.uniform(-1.5, 1.5) * length
        c0 = a + shift * u + gap * perp
        c1 = c0 + (1 if k % 2 else -1) * rng.uniform(0.1, 1.0) * u
        rows.append((a, b, c0, c1))
    a, b, c0, c1 = (np.array(x) for x in zip(*rows))
    bf = brute_segment_distance(a, b, c0, c1)[0]
    rl, ro = 0.05, 0.07
    for k in range(len(rows)):
        d, n, pl, po = capsule_pair(a[k], b[k], rl, c0[k], c1[k], ro)
        assert abs(d - (bf[k] - rl - ro)) <= 1e-9, (k, d, bf[k] - rl - ro)
        P, Q = pl + rl * n, po - ro * n
        assert on_segment(P, a[k], b[k]) <= 1e-12 and on_segment(Q, c0[k], c1[k]) <= 1e-12, k
        assert abs(np.linalg.norm(P - Q) - bf[k]) <= 1e-9
        assert abs(np.linalg.norm(n) - 1.0) <= 1e-12
        if bf[k] > 1e-9:
            np.testing.assert_allclose(n, (P - Q) / bf[k], atol=1e-9)
        if d > 1e-6:
            d_fcl, _, _ = fcl_distance(fcl_segment(a[k], b[k], rl), fcl_segment(c0[k], c1[k], ro))
            assert abs(d - d_fcl) <= 1e-9, (k, d, d_fcl)


@pytest.mark.parametrize("theta", [1e-5, 1e-6, 3e-7, 1e-7])
def test_capsule_pair_nearly_parallel_crossing_axes(theta):
    """Axes at an angle θ that cross (or pass within ≤ 1e-3 m of each other) inside both segments: the
    distance is well-conditioned (the axes' distance, whatever θ) though the crossing point is not.
    Ericson's closed form with the parallel test |d1×d2|² ≤ ε|d1|²|d2|² at ε ~ 1e-16 stays within
    ~1.3e-8 m of the brute force for every θ (cancellation in the general branch ~ 1e-16/θ, the
    parallel branch's error ~ θ·L); tolerance 2e-8 m."""
    rng = np.random.default_rng(SEED + 21)
    rows = []
    for k in range(60):
        u = rng.standard_normal(3)
        u /= np.linalg.norm(u)
        perp = np.cross(u, rng.standard_normal(3))
        perp /= np.linalg.norm(perp)
        a = rng.uniform(-1, 1, 3)
        h = 0.0 if k % 2 == 0 else 10 ** rng.uniform(-9, -3)
        c0 = a + rng.uniform(-0.5, 0.5) * u + h * np.cross(u, perp) - 0.5 * theta * perp
        rows.append((a, a + u, c0, c0 + u + theta * perp))
    a, b, c0, c1 = (np.array(x) for x in zip(*rows))
    bf = brute_segment_distance(a, b, c0, c1)[0]
    rl, ro = 0.05, 0.05
    worst, where = 0.0, 0
    for k in range(len(rows)):
        d, n, _, _ = capsule_pair(a[k], b[k], rl, c0[k], c1[k], ro)
        assert abs(np.linalg.norm(n) - 1.0) <= 1e-12
        if abs(d - (bf[k] - rl - ro)) > worst:
            worst, where = abs(d - (bf[k] - rl - ro)), k
    assert worst <= 2e-8, (f"θ = {theta:g}: distance off by {worst:.3e} m for a = {a[where].tolist()}, "
                           f"b = {b[where].tolist()}, c0 = {c0[where].tolist()}, c1 = {c1[where].tolist()} "
                           f"(brute force: axes {bf[where]:.3e} m apart)")


def test_capsule_pair_intersecting_axes_and_centre_on_axis():
    """Axes that meet (crossing inside, T-junctions at an end, a sphere's centre on the axis interior):
    d = −(r_link + r_obs) exactly, the normal unit and perpendicular to both axes (to the link's for
    a sphere), the witness points r_link and r_obs off the meeting point along ∓n."""
    rng = np.random.default_rng(SEED + 22)
    for k in range(60):
        a, b = rng.uniform(-1, 1, (2, 3))
        s = [0.3, 0.0, 1.0, rng.uniform(0.1, 0.9)][k % 4]
        X = a + s * (b - a)  # the meeting point on the link's axis
        rl, ro = 0.05, 0.08
        if k % 3 == 2:  # a sphere centred on the link's axis (interior or an end)
            c0 = c1 = X
        else:
            w = rng.standard_normal(3)
            tpar = [rng.uniform(0.2, 0.8), 0.0, 1.0][k % 3]
            c0 = X - tpar * w
            c1 = c0 + w
        d, n, pl, po = capsule_pair(a, b, rl, c0, c1, ro)
        assert abs(d + rl + ro) <= 1e-12, (k, d)
        assert abs(np.linalg.norm(n) - 1.0) <= 1e-12
        assert abs(n @ (b - a)) <= 1e-9 * np.linalg.norm(b - a), k
        assert abs(n @ (c1 - c0)) <= 1e-9 * max(np.linalg.norm(c1 - c0), 1.0), k
        np.testing.assert_allclose(pl, X - rl * n, atol=1e-12)
        np.testing.assert_allclose(po, X + ro * n, atol=1e-12)


def test_capsule_pair_sphere_centred_on_axis_end():
    """The case python-fcl's signed query hangs on (not called here): a sphere centred exactly on an
    end of the link's axis. Analytic answer: d = −(r_link + r_s); n unit and ⊥ the axis; p_link = end −
    r_link n, p_obs = centre + r_s n."""
    rng = np.random.default_rng(SEED + 23)
    for k in range(40):
        a, b = rng.uniform(-1, 1, (2, 3))
        if k % 5 == 0:  # axis along a world axis (the choice of n falls back on another world axis)
            b = a + np.eye(3)[k % 3]
        end = (a if k % 2 else b).copy()
        rl, rs = rng.uniform(0.01, 0.3, 2)
        d, n, pl, po = capsule_pair(a, b, rl, end, end, rs)
        assert abs(d + rl + rs) <= 1e-12
        assert abs(np.linalg.norm(n) - 1.0) <= 1e-12
        assert abs(n @ (b - a)) <= 1e-12 * np.linalg.norm(b - a)
        np.testing.assert_allclose(pl, end - rl * n, atol=1e-12)
        np.testing.assert_allclose(po, end + rs * n, atol=1e-12)


def test_capsule_pair_zero_length_segments():
    """A zero-length link axis (a sphere) against spheres and capsules, a capsule against a
    zero-length obstacle axis, two points, two coincident points: python-fcl's sphere–sphere and
    sphere–capsule distances (1e-9 m) where apart, the analytic answer where they coincide."""
    rng = np.random.default_rng(SEED + 24)
    rows = []
    for k in range(90):
        a, c0 = rng.uniform(-1, 1, (2, 3))
        b = a.copy() if k % 3 != 2 else a + rng.uniform(-1, 1, 3)
        c1 = c0 + rng.uniform(-1, 1, 3) if k % 3 == 1 else c0.copy()
        rows.append((a, b, c0, c1))
    a, b, c0, c1 = (np.array(x) for x in zip(*rows))
    bf = brute_segment_distance(a, b, c0, c1)[0]
    rl, ro = 0.05, 0.1
    for k in range(len(rows)):
        d, n, pl, po = capsule_pair(a[k], b[k], rl, c0[k], c1[k], ro)
        assert abs(d - (bf[k] - rl - ro)) <= 1e-9
        assert abs(np.linalg.norm(n) - 1.0) <= 1e-12
        np.testing.assert_allclose(pl - po, d * n, atol=1e-12)
        if d > 1e-6:
            d_fcl, p1, p2 = fcl_distance(fcl_segment(a[k], b[k], rl), fcl_segment(c0[k], c1[k], ro))
            assert abs(d - d_fcl) <= 1e-9
            assert np.linalg.norm(pl - p1) <= 1e-6 and np.linalg.norm(po - p2) <= 1e-6
    # coincident points and a point on a zero-length link
    p = np.array([0.3, -0.2, 0.1])
    d, n, pl, po = capsule_pair(p, p, 0.05, p, p, 0.1)
    assert abs(d + 0.15) <= 1e-15 and abs(np.linalg.norm(n) - 1.0) <= 1e-15
    np.testing.assert_allclose(pl, p - 0.05 * n, atol=1e-15)
    d, n, _, _ = capsule_pair(p, p, 0.05, p - [0.0, 0.0, 0.5], p + [0.0, 0.0, 0.5], 0.1)
    assert abs(d + 0.15) <= 1e-15 and abs(np.linalg.norm(n) - 1.0) <= 1e-15 and abs(n[2]) <= 1e-15


def test_segment_segment_parameters_equal_brute_force():
    """segment_segment's (s, t): the distance of the points they give equals the brute-force minimum
    (1e-12 m) and is below every sample of a 101×101 grid of both parameters; where the minimiser is
    unique and well-conditioned (|sin angle| > 0.1, s, t inside) s and t equal the brute force's to 1e-6."""
    rng = np.random.default_rng(SEED + 25)
    N = 400
    p1, q1, p2, q2 = (rng.uniform(-1, 1, (N, 3)) for _ in range(4))
    # some segments that overlap in projection (interior minima), some parallel, some degenerate
    q2[:50] = p2[:50] + (q1[:50] - p1[:50]) * rng.uniform(-2, 2, (50, 1))
    q1[50:60] = p1[50:60]
    q2[60:70] = p2[60:70]
    bf, s_bf, t_bf = brute_segment_distance(p1, q1, p2, q2)
    well = 0
    for k in range(N):
        s, t = G.segment_segment(p1[k], q1[k], p2[k], q2[k])
        assert 0.0 <= s <= 1.0 and 0.0 <= t <= 1.0
        P, Q = p1[k] + s * (q1[k] - p1[k]), p2[k] + t * (q2[k] - p2[k])
        dist = float(np.linalg.norm(P - Q))
        assert abs(dist - bf[k]) <= 1e-12, (k, dist, bf[k])
        assert dist <= grid_segment_distance(p1[k], q1[k], p2[k], q2[k]) + 1e-15
        u, w = q1[k] - p1[k], q2[k] - p2[k]
        nu, nw = np.linalg.norm(u), np.linalg.norm(w)
        if nu > 0.1 and nw > 0.1 and np.linalg.norm(np.cross(u, w)) > 0.1 * nu * nw:
            assert abs(s - s_bf[k]) <= 1e-6 and abs(t - t_bf[k]) <= 1e-6, (k, s, s_bf[k], t, t_bf[k])
            well += 1
    assert well > 200


def test_sphere_bound_is_a_lower_bound_for_boxes_and_cylinders():
    """sphere_bound with the obstacle's bounding radius never exceeds python-fcl's distance to the box
    or cylinder (separated pairs), and is not vacuous: it is at least the distance less the bounding
    radius (the shape contains its centre). For a sphere it is the exact distance less 1e-9."""
    rng = np.random.default_rng(SEED + 26)
    checked = 0
    for k in range(300):
        a, b = rng.uniform(-1, 1, (2, 3))
        rl = float(rng.uniform(0.02, 0.1))
        c = rng.uniform(-1.5, 1.5, 3)
        if k % 2:
            o = Obstacle("box", c, size=rng.uniform(0.05, 0.6, 3))
        else:
            o = Obstacle("cylinder", c, radius=float(rng.uniform(0.02, 0.3)), length=float(rng.uniform(0.05, 0.8)),
                         axis=rng.standard_normal(3))
        d, _, _ = fcl_distance(fcl_segment(a, b, rl), fcl_obstacle(o, 0.0))
        if d <= 1e-3:
            continue
        bound = G.sphere_bound(np.array([[a, b]]), 0, rl, *c, o.bounding_radius())
        assert bound <= d + 1e-12, (k, o.shape, bound, d)
        assert bound >= d - o.bounding_radius() - GJK_TOL[o.shape], (k, o.shape, bound, d)
        checked += 1
    assert checked > 100
    a, b, c = np.zeros(3), np.array([1.0, 0.0, 0.0]), np.array([0.5, 0.7, 0.0])
    assert abs(G.sphere_bound(np.array([[a, b]]), 0, 0.05, *c, 0.2) - (0.7 - 0.25 - 1e-9)) <= 1e-15


# ---------------------------------------------------------------------------------------------------
# 3. The workspace's state (qpctl.tick + qpctl.kernels.tick.state) against Pinocchio and python-fcl
# ---------------------------------------------------------------------------------------------------
def planar_scene(rng: np.random.Generator) -> list[Obstacle]:
    """Spheres, capsules, boxes and cylinders in the arm's plane (z = 0) within its reach; some move."""
    obs: list[Obstacle] = []
    for k in range(16):
        c = np.append(rng.uniform(-2.5, 2.5, 2), 0.0)
        motion = {}  # each kind: two static, one translating, one swaying
        if k // 4 == 2:
            motion = dict(velocity=np.append(rng.uniform(-0.3, 0.3, 2), 0.0))
        elif k // 4 == 3:
            motion = dict(amplitude=np.append(rng.uniform(-0.2, 0.2, 2), 0.0), frequency=float(rng.uniform(0.2, 2.0)))
        kind = ("sphere", "capsule", "box", "cylinder")[k % 4]
        if kind == "sphere":
            obs.append(Obstacle("sphere", c, radius=float(rng.uniform(0.05, 0.2)), **motion))
        elif kind == "capsule":
            axis = [0.0, 0.0, 1.0] if k % 8 == 1 else np.append(rng.standard_normal(2), 0.0)
            obs.append(Obstacle("capsule", c, radius=float(rng.uniform(0.03, 0.1)), length=float(rng.uniform(0.2, 0.8)),
                                axis=axis, **motion))
        elif kind == "box":
            obs.append(Obstacle("box", c, size=rng.uniform(0.1, 0.4, 3), **motion))
        else:
            axis = [0.0, 0.0, 1.0] if k % 8 == 3 else np.append(rng.standard_normal(2), 0.0)
            obs.append(Obstacle("cylinder", c, radius=float(rng.uniform(0.05, 0.15)), length=float(rng.uniform(0.1, 0.5)),
                                axis=axis, **motion))
    return obs


def panda_scene(rng: np.random.Generator) -> list[Obstacle]:
    """The same mix around the Panda (x, y ∈ [−0.7, 0.7] m, z ∈ [0, 1.1] m)."""
    obs: list[Obstacle] = []
    for k in range(16):
        c = rng.uniform([-0.7, -0.7, 0.0], [0.7, 0.7, 1.1])
        motion = {}  # each kind: two static, one translating, one swaying
        if k // 4 == 2:
            motion = dict(velocity=rng.uniform(-0.2, 0.2, 3))
        elif k // 4 == 3:
            motion = dict(amplitude=rng.uniform(-0.1, 0.1, 3), frequency=float(rng.uniform(0.2, 2.0)))
        kind = ("sphere", "capsule", "box", "cylinder")[k % 4]
        if kind == "sphere":
            obs.append(Obstacle("sphere", c, radius=float(rng.uniform(0.03, 0.1)), **motion))
        elif kind == "capsule":
            obs.append(Obstacle("capsule", c, radius=float(rng.uniform(0.02, 0.06)), length=float(rng.uniform(0.2, 0.6)),
                                axis=rng.standard_normal(3), **motion))
        elif kind == "box":
            obs.append(Obstacle("box", c, size=rng.uniform(0.05, 0.25, 3), **motion))
        else:
            obs.append(Obstacle("cylinder", c, radius=float(rng.uniform(0.03, 0.1)), length=float(rng.uniform(0.1, 0.4)),
                                axis=rng.standard_normal(3), **motion))
    return obs


def reference_pairs(robot: RobotModel, segments: np.ndarray, obstacles: Sequence[Obstacle], t: float
                    ) -> dict[tuple[int, int], tuple[float, float, np.ndarray, np.ndarray]]:
    """Every (link, obstacle) pair by enumeration: {(i, j): (d, tolerance, p_link, p_obs)} — python-fcl's
    distance and nearest points; for sphere and capsule obstacles the distance is the brute-force
    axes' distance less both radii (python-fcl's signed query is only EPA-accurate when penetrating),
    for boxes and cylinders apart the minimised point–solid distance along the axis (solid_reference)."""
    out = {}
    links = [fcl_segment(s[0], s[1], c.radius) for s, c in zip(segments, robot.capsules)]
    exact_pairs, axes = [], []
    for j, o in enumerate(obstacles):
        obj = fcl_obstacle(o, t)
        for i, link in enumerate(links):
            d, p1, p2 = fcl_distance(link, obj)
            out[i, j] = (d, GJK_TOL.get(o.shape, 0.0) if d > 0 else EPA_TOL, p1, p2)
            if o.shape in ("box", "cylinder") and d > 0:
                # python-fcl's GJK stops above the true distance, by up to ~1e-3 m within 0.3 m
                # (test_solids) and more farther away; the minimisation along the axis is exact
                R = np.eye(3) if o.shape == "box" else frame_z_to(o.axis)  # as fcl_obstacle places them
                half = 0.5 * np.asarray(o.size) if o.shape == "box" else np.array([o.radius, o.radius, 0.5 * o.length])
                exact = minimised_distance(o.shape, segments[i, 0], segments[i, 1], robot.capsules[i].radius,
                                           obstacle_centre(o, t), R, half)
                assert -1e-9 <= d - exact <= 1e-3 + 5e-3 * d  # the two references agree
                out[i, j] = (exact, 1e-9, p1, p2)
            if o.shape in ("sphere", "capsule"):
                exact_pairs.append((i, j))
                axes.append((segments[i, 0], segments[i, 1], *obstacle_axis(o, t)))
    if exact_pairs:
        bf = brute_segment_distance(*(np.array(x) for x in zip(*axes)))[0]
        for (i, j), dist in zip(exact_pairs, bf.tolist()):
            d, _, p1, p2 = out[i, j]
            exact = dist - robot.capsules[i].radius - obstacles[j].radius
            assert abs(exact - d) <= (1e-9 if d > 0 else EPA_TOL)  # the two references agree
            out[i, j] = (exact, 1e-9, p1, p2)
    return out


@pytest.mark.parametrize("which", ["planar", "panda"])
def test_world_clearance_is_the_least_distance_over_every_pair(which):
    """The simulators' clearance (WorldClearance: every pair, no cutoff; closed form for spheres and
    capsules, python-fcl for boxes and cylinders) equals the least distance of the enumeration of
    every pair by python-fcl and brute force, on random states of a mixed, partly moving scene, to that
    pair's reference tolerance."""
    rng = np.random.default_rng(SEED + 40 + (which == "panda"))
    robot = planar_arm() if which == "planar" else panda()
    obstacles = planar_scene(rng) if which == "planar" else panda_scene(rng)
    world = WorldClearance(robot, obstacles)
    data = robot.model.createData()
    penetrating = 0
    for _ in range(60):
        q = rng.uniform(-2.5, 2.5, robot.nv)
        t = float(rng.uniform(0.0, 2.0))
        pin.forwardKinematics(robot.model, data, q)
        segments = np.array([[data.oMi[c.joint_id].act(c.p0), data.oMi[c.joint_id].act(c.p1)]
                             for c in robot.capsules])
        ref = reference_pairs(robot, segments, obstacles, t)
        (d_ref, tol, _, _) = min(ref.values(), key=lambda r: r[0])
        assert world(q, t) == pytest.approx(d_ref, abs=max(tol, 1e-9)), (q, t, d_ref, tol)
        penetrating += d_ref < 0
    assert 0 < penetrating < 60  # both kinds of state were checked
    assert WorldClearance(robot, [])(q, 0.0) == math.inf


@pytest.mark.parametrize("which", ["planar", "panda"])
def test_workspace_state_equals_pinocchio_and_fcl(which):
    """Workspace.state(q, v, t) on random states of a scene of spheres, capsules, boxes and cylinders
    (a quarter of them moving): M (crba, symmetrised), N (nonLinearEffects), the task point's x, J
    (getFrameJacobian, LOCAL_WORLD_ALIGNED) and J̇q̇ (getFrameClassicalAcceleration at q̈ = 0) to 1e-12
    relative; the capsules' world end points (oMi.act) and mid-point Jacobians; the obstacles' centres;
    the pairs: the same (link, obstacle) set within the cutoff as the enumeration (pairs within the
    reference's tolerance of the cutoff may go either way), link-major with ascending obstacles, the
    same distances, witness points (python-fcl's nearest points, separated sphere and capsule pairs),
    unit normals with p_link − p_obs = d n, the witness points' Jacobians and drifts (a probe frame at
    p_link) and the clearance."""
    rng = np.random.default_rng(SEED + 30 + (which == "panda"))
    robot = planar_arm() if which == "planar" else panda()
    obstacles = planar_scene(rng) if which == "planar" else panda_scene(rng)
    cutoff = 0.4 if which == "planar" else 0.25
    ws = Workspace(robot, obstacles, None, None, cutoff, barrier_drift=True)
    ref = PinReference(robot)
    kinds_seen: set[str] = set()
    total = 0
    for q, v, t in sample_states(robot, rng, 20):
        assert ws.state(q, v, t) >= 0
        count = int(ws.cnt[codes.CNT_PAIRS])
        ref.at(q, v)
        assert_close(ws.M, ref.M, 1e-12, "M")
        assert_close(ws.N, ref.N, 1e-12, "N")
        x, J, drift = ref.task()
        assert_close(ws.x, x, 1e-12, "x")
        assert_close(ws.J, J, 1e-12, "J")
        assert_close(ws.drift, drift, 1e-12, "J̇q̇")
        assert_close(ws.xdot, J @ v, 1e-12, "ẋ")
        segments = np.array([ref.segment(c.joint_id, c.p0, c.p1) for c in robot.capsules])
        assert_close(ws.segments, segments, 1e-12, "segments")
        for i, c in enumerate(robot.capsules):
            Jm, _ = ref.point(c.joint_id, segments[i].mean(axis=0))
            assert_close(ws.link_jac[i], Jm, 1e-12, f"link {i} mid-point Jacobian")
        centres = np.array([obstacle_centre(o, t) for o in obstacles])
        assert_close(ws.ob_c, centres, 1e-14, "obstacle centres")
        # the pairs
        got = list(zip(ws.pr_link[:count].tolist(), ws.pr_obs[:count].tolist()))
        assert got == sorted(set(got)), "pairs are not link-major with ascending obstacles (or repeat)"
        want = reference_pairs(robot, segments, obstacles, t)
        sure = {p for p, (d, tol, _, _) in want.items() if d < cutoff - tol}
        maybe = {p for p, (d, tol, _, _) in want.items() if d < cutoff + tol}
        assert sure <= set(got) <= maybe, f"pairs {sorted(set(got) ^ sure)} differ"
        for r, (i, j) in enumerate(got):
            d_ref, tol, p1, p2 = want[i, j]
            d, n, pl, po = ws.pr_d[r], ws.pr_n[r], ws.pr_pl[r], ws.pr_po[r]
            assert abs(d - d_ref) <= tol, (i, j, obstacles[j].shape, d, d_ref)
            assert abs(np.linalg.norm(n) - 1.0) <= 1e-9
            if obstacles[j].shape in ("sphere", "capsule"):
                np.testing.assert_allclose(pl - po, d * n, atol=1e-12)
                if d > 1e-6:
                    assert np.linalg.norm(pl - p1) <= 1e-6 and np.linalg.norm(po - p2) <= 1e-6, (i, j)
            Jp, ap = ref.point(robot.capsules[i].joint_id, pl)
            assert_close(ws.pr_jac[r], Jp, 1e-12, f"pair ({i}, {j}) witness Jacobian")
            assert_close(ws.pr_drift[r], ap, 1e-10, f"pair ({i}, {j}) witness drift")
            kinds_seen.add(obstacles[j].shape + (" moving" if obstacles[j].moving else ""))
        total += count
        clearance = min((d for d, _, _, _ in want.values() if d < cutoff), default=np.inf)
        if clearance == np.inf:
            assert ws.fpar[codes.FP_CLEARANCE] == np.inf
        else:
            assert abs(ws.fpar[codes.FP_CLEARANCE] - clearance) <= EPA_TOL
        assert ws.fpar[codes.FP_CLEARANCE] == (ws.pr_d[:count].min() if count else np.inf)
    # the scene exercised every kind of pair, static and moving
    assert {k.split()[0] for k in kinds_seen} == {"sphere", "capsule", "box", "cylinder"}, kinds_seen
    assert {"sphere moving", "capsule moving"} & kinds_seen, kinds_seen
    assert total > 20


# ---------------------------------------------------------------------------------------------------
# 4. The broad-phase grid
# ---------------------------------------------------------------------------------------------------
def crowd(rng: np.random.Generator, count: int, moving: int) -> list[Obstacle]:
    """``count`` small spheres and capsules around the Panda (some beyond its reach), the first
    ``moving`` of them moving."""
    obs = []
    for k in range(count):
        c = rng.uniform([-1.2, -1.2, -0.3], [1.2, 1.2, 1.4])
        motion = {}
        if k < moving:
            motion = (dict(velocity=rng.uniform(-0.3, 0.3, 3)) if k % 2 else
                      dict(amplitude=rng.uniform(-0.2, 0.2, 3), frequency=float(rng.uniform(0.2, 2.0))))
        if k % 3:
            obs.append(Obstacle("sphere", c, radius=float(rng.uniform(0.01, 0.05)), **motion))
        else:
            obs.append(Obstacle("capsule", c, radius=float(rng.uniform(0.01, 0.03)), length=float(rng.uniform(0.05, 0.4)),
                                axis=rng.standard_normal(3), **motion))
    return obs


def test_broadphase_grid_lists_the_same_pairs():
    """A scene of 300 spheres and capsules (20 moving) around the Panda: with the grid and without it,
    the same pairs (link, obstacle, distance, normal — bit for bit: the same kernel on the same
    inputs) at 40 random states and times; the grid has many cells, so it does prune."""
    rng = np.random.default_rng(SEED + 40)
    robot = panda()
    obstacles = crowd(rng, 300, 20)
    cutoff = 0.15
    grid = Workspace(robot, obstacles, None, None, cutoff, broadphase=True)
    plain = Workspace(robot, obstacles, None, None, cutoff, broadphase=False)
    assert grid.grid_dims.prod() > 50 and plain.grid_dims[0] == 0
    total = moving = 0
    for q, v, t in sample_states(robot, rng, 40):
        t *= 3.0
        assert grid.state(q, v, t) >= 0 and plain.state(q, v, t) >= 0
        k = int(plain.cnt[codes.CNT_PAIRS])
        assert int(grid.cnt[codes.CNT_PAIRS]) == k
        assert np.array_equal(grid.pr_link[:k], plain.pr_link[:k])
        assert np.array_equal(grid.pr_obs[:k], plain.pr_obs[:k])
        assert np.array_equal(grid.pr_d[:k], plain.pr_d[:k])
        assert np.array_equal(grid.pr_n[:k], plain.pr_n[:k])
        assert grid.fpar[codes.FP_CLEARANCE] == plain.fpar[codes.FP_CLEARANCE]
        total += k
        moving += int(np.count_nonzero(plain.pr_obs[:k] < 20))
    assert total > 200 and moving > 0, (total, moving)


def test_broadphase_auto_uses_the_grid_above_the_threshold():
    """broadphase=None: no grid up to GRID_MIN_OBSTACLES static obstacles (moving ones do not count),
    a grid above."""
    rng = np.random.default_rng(SEED + 41)
    robot = planar_arm()
    static = [Obstacle("sphere", np.append(rng.uniform(-2, 2, 2), 0.0), radius=0.05)
              for _ in range(GRID_MIN_OBSTACLES + 1)]
    moving = [Obstacle("sphere", [0.0, 2.5, 0.0], radius=0.05, velocity=[0.1, 0.0, 0.0]) for _ in range(5)]

    def has_grid(obs: list[Obstacle]) -> bool:
        return bool(Workspace(robot, obs, None, None, 0.3).grid_dims[0] > 0)

    assert not has_grid(static[:GRID_MIN_OBSTACLES])
    assert not has_grid(static[:GRID_MIN_OBSTACLES] + moving)
    assert has_grid(static)
    assert has_grid(static + moving)


# ---------------------------------------------------------------------------------------------------
# 5. The closed forms: compiled step against the numpy law (qpctl.law) on the same state
# ---------------------------------------------------------------------------------------------------
def check_law(ctrl: PaperController, states: Sequence[tuple[np.ndarray, np.ndarray, float]]) -> dict[str, int]:
    """ctrl.step (compiled) against ctrl.control(ctrl.dynamics.compute(...)) (numpy): τ, q̈ and e_N
    to 1e-9 relative, x and the reference exactly as computed, the same singular flag. Returns how
    many states had an active obstacle sensor (g ≠ 0) and how many were singular."""
    seen = {"active": 0, "singular": 0}
    for q, v, t in states:
        out = ctrl.step(q, v, t)
        tau, qdd, e_null, singular = out.tau.copy(), out.qdd.copy(), out.e_null.copy(), bool(out.singular)
        g = ctrl.workspace().g.copy()
        ref = ctrl.control(ctrl.dynamics.compute(q, v, t))
        where = f"{ctrl.kind} at q={q.tolist()}, v={v.tolist()}, t={t}"
        assert_close(tau, ref.tau, 1e-9, f"τ, {where}")
        assert_close(qdd, ref.qdd, 1e-9, f"q̈, {where}")
        assert_close(e_null, ref.e_null, 1e-9, f"e_N, {where}")
        assert_close(out.x, ref.x, 1e-12, f"x, {where}")
        for got, want in zip(out.ref, ref.ref):
            assert_close(got, want, 1e-12, f"reference, {where}")
        assert singular == ref.singular, f"singular {singular} != {ref.singular}, {where}"
        seen["active"] += bool(np.any(g))
        seen["singular"] += singular
    return seen


def states_near(ctrl: PaperController, rng: np.random.Generator, k: int, v_scale: float = 1.0,
                tries: int = 400) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """k random states, at least half of them with a link within d_influence of an obstacle."""
    near, rest = [], []
    ws = Workspace(ctrl.robot, ctrl.obstacles, None, None, ctrl.gains.d_influence)
    for q, v, t in sample_states(ctrl.robot, rng, tries, v_scale):
        assert ws.state(q, v, t) >= 0
        (near if ws.cnt[codes.CNT_PAIRS] and len(near) < (k + 1) // 2 else rest).append((q, v, t))
        if len(near) >= (k + 1) // 2 and len(near) + len(rest) >= k:
            break
    assert len(near) >= (k + 1) // 2, "too few states near an obstacle"
    return near + rest[: k - len(near)]


def panda_with_spheres(rng: np.random.Generator, v_ref: bool) -> tuple[RobotModel, WaypointPath, list[Obstacle]]:
    robot = panda()
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, robot.q_home)
    start = data.oMf[robot.ee_frame_id].translation.copy()
    path = WaypointPath([start, start + [0.15, 0.25, -0.1], start + [0.0, 0.1, 0.2]], duration=3.0)
    obstacles = []
    for k in range(10):
        motion = dict(velocity=rng.uniform(-0.2, 0.2, 3)) if k % 3 == 0 else {}
        own = ({0: 0.0, 1: 1.5, 2: 0.1}.get(k % 4)) if v_ref else None
        obstacles.append(Obstacle("sphere", rng.uniform([-0.6, -0.6, 0.1], [0.6, 0.6, 1.0]),
                                  radius=float(rng.uniform(0.04, 0.1)), v_ref=own, **motion))
    return robot, path, obstacles


@pytest.mark.parametrize("law", [PaperController, HsuController], ids=["paper", "hsu"])
def test_closed_forms_equal_numpy_law_on_scenarios(law):
    """The paper scenario and panda_canopy: compiled τ equals the numpy law's to 1e-9 relative on 16
    random states each, half of them with the obstacle sensor active."""
    rng = np.random.default_rng(SEED + 50)
    for name in ("paper", "panda_canopy"):
        ctrl = Scenario.load(name).build_controller(law.kind)
        assert type(ctrl) is law
        seen = check_law(ctrl, states_near(ctrl, rng, 16))
        assert seen["active"] >= 6, (name, seen)


@pytest.mark.parametrize("law", [PaperController, HsuController], ids=["paper", "hsu"])
@pytest.mark.parametrize("variant", ["plain", "jdot_en", "obstacle_v_ref"])
def test_closed_forms_equal_numpy_law_panda_spheres(law, variant):
    """A Panda among ten spheres (some moving): the plain gains, LawGains(jdot_en=True) (the J̇e_N
    term of eq. 18) and per-obstacle v_ref (0, 1.5 and 0.1 m/s on three quarters of them)."""
    rng = np.random.default_rng(SEED + 51)
    robot, path, obstacles = panda_with_spheres(rng, v_ref=variant == "obstacle_v_ref")
    gains = LawGains(kn=15.0, v_ref=0.6, d_influence=0.25, d_safe=0.04, jdot_en=variant == "jdot_en")
    ctrl = law(robot, path, obstacles, gains)
    if variant == "obstacle_v_ref":
        assert ctrl.gains.obstacle_v_ref and np.isnan(ctrl.gains.obstacle_v_ref[3])
    states = states_near(ctrl, rng, 12)
    seen = check_law(ctrl, states)
    assert seen["active"] >= 5, seen
    if variant == "obstacle_v_ref":  # the per-obstacle speeds change the answer (so they were read)
        plain = law(robot, path, [Obstacle(o.shape, o.position, radius=o.radius, velocity=o.velocity)
                                  for o in obstacles], gains)
        assert any(np.abs(plain.step(q, v, t).tau - ctrl.step(q, v, t).tau).max() > 1e-6 for q, v, t in states)
    if variant == "jdot_en":  # likewise J̇e_N
        plain = law(robot, path, obstacles, LawGains(kn=15.0, v_ref=0.6, d_influence=0.25, d_safe=0.04))
        assert any(np.abs(plain.step(q, v, t).tau - ctrl.step(q, v, t).tau).max() > 1e-6 for q, v, t in states)


@pytest.mark.parametrize("law", [PaperController, HsuController], ids=["paper", "hsu"])
def test_closed_forms_near_a_singularity(law):
    """The paper's arm stretched straight (q = 0), folded back (q₂ = π), and a hair (1e-7 rad) from
    straight: the damped pseudo-inverses agree with numpy's and both report the tick singular; at
    regular states both report it regular. (τ agrees to ~1.5e-10 relative here, against ~1e-14 at
    regular states: the damped inverse's sensitivity to σ_min, see the module docstring.)"""
    rng = np.random.default_rng(SEED + 52)
    ctrl = Scenario.load("paper").build_controller(law.kind)
    singular = [np.array(q, float) for q in ([0.0, 0.0, 0.0], [0.4, 0.0, 0.0], [0.0, np.pi, 0.0],
                                             [-0.3, 1e-7, -1e-7], [np.pi / 2, 0.0, np.pi])]
    states = [(q, rng.uniform(-1, 1, 3), float(rng.uniform(0, 5))) for q in singular]
    seen = check_law(ctrl, states)
    assert seen["singular"] == len(states), seen
    regular = [(np.array([0.5, 1.2, -0.8]), rng.uniform(-1, 1, 3), 1.0), (np.array([2.0, -1.0, 1.5]), np.zeros(3), 2.0)]
    assert check_law(ctrl, regular)["singular"] == 0


def test_reference_velocity_with_an_obstacle_whose_v_ref_is_zero():
    """The smallest case of the per-obstacle v_ref: the paper's arm at its start pose with sphere 0
    (v_ref = 0) 0.07 m from link 1 and sphere 1 (the controller's v_ref = 1 m/s) 0.07 m from link 3.
    qpctl.law's g = argmin Σ_k α_k‖J_k q̇ − u_k‖² + λ²‖q̇‖² keeps sphere 0's pair with u = 0 (a "hold
    still" row); the compiled g must be the same (1e-9 relative), and so must τ."""
    robot = planar_arm()
    path = WaypointPath([[-1.0, -2.0], [1.0, -1.5]], duration=4.0)
    obstacles = [Obstacle("sphere", [-0.5, 0.2], radius=0.08, v_ref=0.0), Obstacle("sphere", [-1.2, -1.5], radius=0.08)]
    ctrl = PaperController(robot, path, obstacles, LawGains(v_ref=1.0, d_influence=0.3, d_safe=0.05))
    q, v = np.array([np.pi, np.pi / 2, 0.0]), np.zeros(3)
    tau = ctrl.step(q, v, 0.0).tau.copy()
    ws = ctrl.workspace()
    k = int(ws.cnt[codes.CNT_PAIRS])
    assert list(zip(ws.pr_link[:k].tolist(), ws.pr_obs[:k].tolist())) == [(0, 0), (2, 1)]
    state = ctrl.dynamics.compute(q, v, 0.0)
    terms = law_terms(state, ctrl.path(0.0), ctrl.gains, weighted=True)
    assert_close(ws.g, terms.g, 1e-9, "g")
    assert_close(tau, ctrl.control(state).tau, 1e-9, "τ")


# ---------------------------------------------------------------------------------------------------
# 6. The QP assembly: compiled rows against the Formulation, compiled torques against the Python path
# ---------------------------------------------------------------------------------------------------
PROBLEM_FIELDS = ("P", "c", "A", "b", "C", "l", "u", "lb", "ub")
QP_SCENARIOS = {
    "panda_canopy": ("panda_canopy", []),
    "panda_canopy-rigid": ("panda_canopy", ['controller.barrier_drift="rigid"']),
    "paper-posture-limits": ("paper", ["controller.posture_weight=50.0", "robot.tau_max=[2500.0, 1500.0, 700.0]",
                                       "robot.v_max=3.0"]),
}


def qp_controller(key: str, solver: str | None = None) -> QPController:
    name, overrides = QP_SCENARIOS[key]
    ctrl = Scenario.load(name, overrides=overrides).build_controller("qp", solver=solver)
    assert isinstance(ctrl, QPController) and ctrl.workspace().spec is not None  # the compiled path
    return ctrl


def assert_entrywise(got: np.ndarray, want: np.ndarray, rtol: float, what: str) -> None:
    """Entry-wise |got − want| ≤ rtol·|want| (+ 1e-14 of the array's largest entry, for exact zeros
    against rounding-level values); the same infinities."""
    got, want = np.asarray(got, float), np.asarray(want, float)
    assert got.shape == want.shape, f"{what}: shape {got.shape} != {want.shape}"
    fin = np.isfinite(want)
    assert np.array_equal(got[~fin], want[~fin]) and np.isfinite(got[fin]).all(), f"{what}: infinities differ"
    floor = 1e-14 * float(np.max(np.abs(want[fin]), initial=0.0))
    bad = np.abs(got[fin] - want[fin]) > rtol * np.abs(want[fin]) + floor
    assert not bad.any(), f"{what}: {np.count_nonzero(bad)} entries differ, e.g. {got[fin][bad][:3]} != {want[fin][bad][:3]}"


@pytest.mark.parametrize("key", list(QP_SCENARIOS))
def test_qp_assembly_equals_formulation(key):
    """After ctrl.step (compiled), ctrl.last_problem (views onto the buffers the kernel wrote) equals
    Formulation.build(dynamics.compute(q, v, t), law_terms(...)) of the same layout (relaxed, or the task
    hard where the tick's answer came from it) entry-wise to 1e-9
    relative, infinities equal; 8 random states, most with obstacle rows active. The scenarios: the
    Panda among branches and leaves (torque, joint and barrier rows, exact and rigid barrier drift),
    the paper's arm with a posture task, torque limits and speed limits (the ∞ − ∞ joint bounds)."""
    rng = np.random.default_rng(SEED + 60)
    ctrl = qp_controller(key)
    names = [c.name for c in ctrl.constraints]
    assert names == ["torque_limits", "joint_limits", "obstacles", "self_collision"], names
    assert ("posture" in [t.name for t in ctrl.tasks]) == key.startswith("paper")
    form = ctrl.formulation()
    barrier_rows = form.barrier_rows
    active = 0
    for q, v, t in states_near(ctrl, rng, 8, 0.5):
        ctrl.step(q, v, t)
        problem = ctrl.last_problem
        assert problem is not None
        got = {f: np.array(getattr(problem, f)) for f in PROBLEM_FIELDS}
        state = ctrl.dynamics.compute(q, v, t)
        terms = law_terms(state, ctrl.path(t), ctrl.gains, weighted=True)
        relaxed = problem.n_var > state.n  # the layout the tick's answer came from (the task hard first: no slack)
        want = form.build(state, terms, relax=relaxed)
        for f in PROBLEM_FIELDS:
            assert_entrywise(got[f], getattr(want, f), 1e-9, f"{key}: {f} at q={q.tolist()}, v={v.tolist()}, t={t}")
        active += int(np.isfinite(want.l[barrier_rows]).any())
    assert active >= 4, active


@pytest.mark.parametrize("key", ["panda_canopy", "paper-posture-limits"])
def test_compiled_joint_bounds_outside_the_limits(key):
    """States outside the joint limits (issue 22's guard: no state of the test above lies there):
    positions up to 1.5 rad beyond either limit, speeds up to 3 × v_max. The compiled bounds on q̈ (the
    problem's lb, ub after ctrl.step) equal JointLimit.compute to 1e-12, lie within ±q̈_max with
    lb ≤ ub; and (independently of both) a joint far below q_min at rest, where the position barrier
    asks k₀·1.5 rad ≫ q̈_max, gets lb = ub = +q̈_max (above q_max: −q̈_max)."""
    rng = np.random.default_rng(SEED + 63)
    ctrl = qp_controller(key)
    robot, n = ctrl.robot, ctrl.robot.nv
    limit = next(c for c in ctrl.constraints if c.name == "joint_limits")
    qdd = np.broadcast_to(np.inf if robot.qdd_max is None else robot.qdd_max, (n,))
    lo = np.where(np.isfinite(robot.q_min), robot.q_min, -np.pi)
    hi = np.where(np.isfinite(robot.q_max), robot.q_max, np.pi)
    vmax = np.where(np.isfinite(robot.v_max), robot.v_max, 2.0)
    for k in range(12):
        q, v = rng.uniform(lo, hi), rng.uniform(-3, 3, n) * vmax
        out = rng.random(n) < 0.5
        side = rng.random(n) < 0.5
        q = np.where(out & side, lo - rng.uniform(0.1, 1.5, n), np.where(out, hi + rng.uniform(0.1, 1.5, n), q))
        if k < 2:  # every joint 1.5 rad beyond one limit, at rest
            q, v = (lo - 1.5 if k == 0 else hi + 1.5), np.zeros(n)
        ctrl.step(q, v, 0.1)
        lb, ub = np.array(ctrl.last_problem.lb[:n]), np.array(ctrl.last_problem.ub[:n])
        want = limit.compute(ctrl.dynamics.compute(q, v, 0.1), None)  # type: ignore[arg-type]
        where = f"{key} at q={q.tolist()}, v={v.tolist()}"
        assert_close(lb, want.lower, 1e-12, f"lb, {where}")
        assert_close(ub, want.upper, 1e-12, f"ub, {where}")
        assert np.all(lb <= ub) and np.all(lb >= -qdd) and np.all(ub <= qdd), where
        if k < 2 and np.isfinite(robot.q_min).all() and np.isfinite(qdd).all():
            edge = qdd if k == 0 else -qdd
            assert np.array_equal(lb, edge) and np.array_equal(ub, edge), where


def test_qp_rigid_and_exact_barrier_drift_differ():
    """The two barrier drifts give different obstacle rows at the same moving state (so each of the
    comparisons above checks the one its setting asks for)."""
    rng = np.random.default_rng(SEED + 61)
    exact, rigid = qp_controller("panda_canopy"), qp_controller("panda_canopy-rigid")
    rows = exact.formulation().barrier_rows
    differ = 0
    for q, v, t in states_near(exact, rng, 6, 1.0):
        exact.step(q, v, t)
        l_exact = np.array(exact.last_problem.l[rows])
        rigid.step(q, v, t)
        l_rigid = np.array(rigid.last_problem.l[rows])
        fin = np.isfinite(l_exact)
        assert np.array_equal(fin, np.isfinite(l_rigid))
        differ += bool(np.any(np.abs(l_exact[fin] - l_rigid[fin]) > 1e-6))
    assert differ >= 2, differ


class SubAcceleration(AccelerationTask):
    """A standard task under another type: the controller must take the Python formulation."""


class SubEndEffector(EndEffectorTask):
    pass


class SubPosture(PostureTask):
    pass


class SubDamping(DampingTask):
    pass


@pytest.mark.parametrize("solver", ["daqp", "proxqp"])
@pytest.mark.parametrize("key", ["panda_canopy", "paper-posture-limits"])
def test_qp_compiled_torque_equals_python_path(key, solver):
    """The same QP on the compiled path (standard tasks) and on the Python path (the same tasks under
    subclasses, so compiled_spec refuses them): torques to 1e-8 relative and the same fallback (if
    any) over 8 ticks, each controller warm-starting from its own previous tick."""
    rng = np.random.default_rng(SEED + 62)
    fast = qp_controller(key, solver)
    tasks: list = []
    for task in fast.tasks:
        if type(task) is AccelerationTask:
            tasks.append(SubAcceleration(task.weight))
        elif type(task) is EndEffectorTask:
            tasks.append(SubEndEffector(task.slack_l1, task.slack_l2))
        elif type(task) is DampingTask:
            tasks.append(SubDamping(task.weight, task.gain))
        else:
            tasks.append(SubPosture(task.q_ref, task.weight, task.kp, task.kd))
    slow = QPController(fast.robot, fast.path, fast.obstacles, fast.gains, QPConfig(**vars(fast.config)), tasks=tasks,
                        broadphase=fast.broadphase)
    assert slow.workspace().spec is None and fast.workspace().spec is not None
    assert [c.name for c in slow.constraints] == [c.name for c in fast.constraints]
    assert slow.solver == fast.solver == solver
    for q, v, t in states_near(fast, rng, 8, 0.5):
        a, b = fast.step(q, v, t), slow.step(q, v, t)
        where = f"{key}/{solver} at q={q.tolist()}, v={v.tolist()}, t={t}"
        assert a.info.get("fallback") == b.info.get("fallback"), where
        assert_close(a.tau, b.tau, 1e-8, f"τ, {where}")


# ---------------------------------------------------------------------------------------------------
# 7. bind_pinocchio: live numpy views of pin.Data
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("which", ["planar", "panda"])
def test_bind_pinocchio_views_are_live(which):
    """After rigid_pass (crba, nonLinearEffects) at random states the views equal what a separate
    data's computeAllTerms gives — oMi[j].homogeneous, J, M's upper triangle, nle, and data.a[j] once
    the view's a_gf is given back gravity (a = a_gf + Rᵀg, angular parts equal) — and equal data.a_gf
    bit for bit, call after call (they are the same memory)."""
    robot = planar_arm() if which == "planar" else panda()
    model = robot.model
    data, full = model.createData(), model.createData()
    views = bind_pinocchio(model, data)
    g = model.gravity.linear
    rng = np.random.default_rng(SEED + 70)
    previous = None
    for q, v, _ in sample_states(robot, rng, 6):
        rigid_pass(model, data, q, v)
        pin.computeAllTerms(model, full, q, v)
        for j in range(model.njoints):
            H = np.eye(4)
            H[:3, :3] = views["oMi"][j, :9].reshape(3, 3).T  # column-major rotation
            H[:3, 3] = views["oMi"][j, 9:]
            assert np.array_equal(H, full.oMi[j].homogeneous), j
            assert np.array_equal(views["acc_gf"][j], data.a_gf[j].vector), j
            a = views["acc_gf"][j].copy()
            a[:3] += full.oMi[j].rotation.T @ g
            np.testing.assert_allclose(a, full.a[j].vector, rtol=0, atol=1e-12 * max(1.0, np.abs(full.a[j].vector).max()))
        assert np.array_equal(views["Jt"].T, full.J)
        assert np.array_equal(np.triu(views["Mt"].T), np.triu(full.M))
        np.testing.assert_allclose(views["nle"], full.nle, rtol=1e-12, atol=1e-12)
        if previous is not None:  # the state moved, so did the views
            assert not np.array_equal(previous, views["oMi"])
        previous = views["oMi"].copy()


@pytest.mark.parametrize("which", ["planar", "panda"])
def test_gravity_changed_after_the_workspace_is_built_counts(which):
    """The kernels give a_gf its gravity back from the model itself (bind_pinocchio's live view), so a
    workspace built before ``model.gravity`` changes still gives J̇q̇ — independent of gravity — as
    Pinocchio's classical acceleration at q̈ = 0 (forwardKinematics, no gravity involved), and N as
    nonLinearEffects under the new gravity on a separate model. (A copy taken at the build gave the
    drift off by R(g_new − g_old) terms.)"""
    robot = planar_arm() if which == "planar" else panda()
    model = robot.model
    g0 = model.gravity.linear.copy()
    ws = Workspace(robot, [], None, None, 0.25)
    assert ws.model is model
    ref = PinReference(robot)
    other = pin.Model(model)
    rng = np.random.default_rng(SEED + 71)
    try:
        for g in ([0.0, 0.0, -3.7], [1.5, -2.0, 0.5], [0.0, 0.0, 0.0]):
            model.gravity = pin.Motion(np.array(g), np.zeros(3))
            other.gravity = pin.Motion(np.array(g), np.zeros(3))
            np.testing.assert_array_equal(ws.gravity, g)
            for q, v, t in sample_states(robot, rng, 3):
                assert ws.state(q, v, t) >= 0
                ref.at(q, v)
                _, _, drift = ref.task()
                assert_close(ws.drift, drift, 1e-12, f"J̇q̇ under g = {g}")
                N = pin.nonLinearEffects(other, other.createData(), q, v)
                assert_close(ws.N, N, 1e-12, f"N under g = {g}")
    finally:
        model.gravity = pin.Motion(g0, np.zeros(3))


# ---------------------------------------------------------------------------------------------------
# 8. The on-disk kernel cache, seen from a fresh worker process
# ---------------------------------------------------------------------------------------------------
CHILD = textwrap.dedent("""
    import json
    import numpy as np
    import qpctl
    from qpctl import Scenario
    from qpctl.kernels import tick as K
    from qpctl.solvers import daqp_native
    for kind in ("paper", "qp"):
        ctrl = Scenario.load("paper").build_controller(kind)
        for t in (0.5, 0.501):  # the QP's first tick sets DAQP up, the second runs the whole tick in one kernel
            ctrl.step(np.array([np.pi, np.pi / 2, 0.0]), np.zeros(3), t)
    # what the ticks dispatch: the paper law one call; the QP's first tick the state, the rows, then
    # DAQP's setup and solve of the hard QP (the task without slack), later ones one call on DAQP's C API
    # (tick_qp; or, without it, daqp.Model's path)
    kernels = [("tick_closed_form", K.tick_closed_form), ("state", K.state), ("qp_terms_and_build", K.qp_terms_and_build)]
    if daqp_native.available():
        kernels += [("native_solve", K.native_solve), ("tick_qp", K.tick_qp)]
    else:
        kernels += [("qp_finish", K.qp_finish)]
    out = {name: [sum(k.stats.cache_hits.values()), sum(k.stats.cache_misses.values()), k.stats.cache_path]
           for name, k in kernels}
    # whatever else ran (the fallbacks' kernels, if a solve failed) was loaded, not compiled, too
    import pkgutil, importlib, qpctl.kernels
    stage_modules = [importlib.import_module("qpctl.kernels." + m.name) for m in pkgutil.iter_modules(qpctl.kernels.__path__)]
    out["_misses"] = sum(sum(k.stats.cache_misses.values()) for mod in stage_modules for k in vars(mod).values()
                         if hasattr(k, "stats"))
    out["module"] = qpctl.__file__
    print(json.dumps(out))
""")


def test_kernels_load_from_the_cache_in_a_worker_process(tmp_path):
    """Once this process has compiled (or loaded) the tick's kernels, a fresh interpreter that imports
    the installed package (run from elsewhere, so not from the source tree on sys.path), builds the
    paper scenario's closed-form and QP controllers and runs a tick of each loads the kernels from the
    on-disk cache: cache hits, no misses (a miss is a compilation)."""
    for kind in ("paper", "qp"):  # compiled (and cached) here, if no earlier test did
        ctrl = Scenario.load("paper").build_controller(kind)
        for t in (0.5, 0.501):
            ctrl.step(np.array([np.pi, np.pi / 2, 0.0]), np.zeros(3), t)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run([sys.executable, "-c", CHILD], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out.pop("module").endswith(os.path.join("qpctl", "__init__.py"))
    assert out.pop("_misses") == 0
    for name, (hits, misses, path) in out.items():
        assert hits > 0 and misses == 0, (name, hits, misses, path)
        assert os.path.isdir(path), path


def test_finite_problem_matches_numpys_finiteness_tests():
    """The QP's data check (read as the values' bits) against numpy: False exactly when H, f or a row
    holds a NaN or ±∞, or a bound holds a NaN (±∞ in a bound means "no bound"); every kind of IEEE
    value tried in every array, including the largest finite double, −0 and a subnormal."""
    from qpctl.kernels.finish import finite_problem

    rng = np.random.default_rng(3)
    H, f, rows = rng.standard_normal((7, 7)), rng.standard_normal(7), rng.standard_normal((51, 7))
    bu = rng.standard_normal(58)
    bl = bu - 1.0
    bu[3], bl[5] = np.inf, -np.inf
    specials = [np.nan, -np.nan, np.inf, -np.inf, np.finfo(float).max, -np.finfo(float).max, -0.0, 5e-324]
    seen = {True: 0, False: 0}
    for k in range(5):
        for value in specials:
            for _ in range(4):
                arrs = [H.copy(), f.copy(), rows.copy(), bu.copy(), bl.copy()]
                flat = arrs[k].reshape(-1)
                flat[rng.integers(flat.size)] = value
                expected = bool(all(np.isfinite(a).all() for a in arrs[:3]) and not np.isnan(arrs[3]).any()
                                and not np.isnan(arrs[4]).any())
                assert finite_problem(*arrs) is expected, (k, value)
                seen[expected] += 1
    assert seen[True] and seen[False]
