"""The weighted pseudo-inverse (paper eq. 5–6) against its defining conditions and the explicit formula.

For full-rank J (m × n, m < n) and SPD W, J⁺ = W⁻¹Jᵀ(JW⁻¹Jᵀ)⁻¹ is the unique matrix with
J J⁺ J = J, J⁺ J J⁺ = J⁺, (J J⁺)ᵀ = J J⁺ and (W J⁺ J)ᵀ = W J⁺ J (eq. 5 in the metric W), and
J J⁺ = I. The checks are relative to ‖J‖‖J⁺‖-sized quantities at 1e-9: the SVD route is backward
stable, so only the conditioning of W (≲ 1e4 here) times machine precision is lost.
"""

from __future__ import annotations

import numpy as np
import pytest

from qpctl.dynamics import Dynamics
from qpctl.linalg import weighted_pinv

TOL = 1e-9


def _spd(rng: np.random.Generator, n: int, cond: float = 1e3) -> np.ndarray:
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return Q @ np.diag(np.geomspace(1.0, cond, n)) @ Q.T


def _check_conditions(J: np.ndarray, Jp: np.ndarray, W: np.ndarray) -> None:
    scale = np.linalg.norm(J, 2) * np.linalg.norm(Jp, 2)
    np.testing.assert_allclose(J @ Jp @ J, J, atol=TOL * scale * np.linalg.norm(J, 2))
    np.testing.assert_allclose(Jp @ J @ Jp, Jp, atol=TOL * scale * np.linalg.norm(Jp, 2))
    JJp = J @ Jp
    np.testing.assert_allclose(JJp, JJp.T, atol=TOL * scale)
    WJpJ = W @ Jp @ J
    np.testing.assert_allclose(WJpJ, WJpJ.T, atol=TOL * scale * np.linalg.norm(W, 2))
    np.testing.assert_allclose(JJp, np.eye(J.shape[0]), atol=TOL * scale)


def _explicit(J: np.ndarray, W: np.ndarray) -> np.ndarray:
    Wi_Jt = np.linalg.solve(W, J.T)
    return Wi_Jt @ np.linalg.inv(J @ Wi_Jt)


@pytest.mark.parametrize("weight", ["identity", "inertia", "cholesky"])
@pytest.mark.parametrize("shape", [(2, 3), (3, 7), (3, 5)])
def test_four_conditions_and_explicit_formula_random(rng, weight, shape):
    m, n = shape
    for _ in range(5):
        J = rng.normal(size=(m, n))
        if weight == "identity":
            W, factor = np.eye(n), None
        elif weight == "inertia":  # W = MᵀM, given by its factor M (symmetric)
            M = _spd(rng, n, 1e2)
            W, factor = M.T @ M, M
        else:  # a general SPD W, given by its Cholesky factor L (W = L Lᵀ)
            W = _spd(rng, n, 1e3)
            factor = np.linalg.cholesky(W)
        P = weighted_pinv(J, factor)
        assert not P.singular
        assert P.matrix.shape == (n, m)
        _check_conditions(J, P.matrix, W)
        np.testing.assert_allclose(P.matrix, _explicit(J, W), rtol=1e-8, atol=1e-10 * np.abs(P.matrix).max())
        s = np.linalg.svd(J @ np.linalg.inv(factor).T if factor is not None else J, compute_uv=False)
        assert P.sigma_ratio == pytest.approx(s[-1] / s[0], rel=1e-10)


def test_identity_weight_is_moore_penrose(rng):
    J = rng.normal(size=(2, 3))
    np.testing.assert_allclose(weighted_pinv(J).matrix, np.linalg.pinv(J), atol=1e-12)


def test_weighted_pinv_minimises_the_weighted_norm(rng):
    """J⁺ b is the least-‖·‖_W solution of J x = b: no null-space step lowers xᵀWx (a second characterisation)."""
    J = rng.normal(size=(3, 7))
    W = _spd(rng, 7)
    b = rng.normal(size=3)
    x = weighted_pinv(J, np.linalg.cholesky(W)).matrix @ b
    _, _, Vt = np.linalg.svd(J)
    for z in Vt[3:]:  # null-space directions of J
        assert abs(x @ W @ z) < 1e-9 * np.sqrt(x @ W @ x) * np.sqrt(z @ W @ z)


def test_planar_arm_inertia_weighted(planar, random_states):
    """On the real arm: W = MᵀM from Pinocchio's M."""
    dyn = Dynamics(planar)
    for q, v in random_states(planar, 5):
        s = dyn.compute(q, v)
        P = weighted_pinv(s.J, s.M)
        if P.singular:
            continue
        _check_conditions(s.J, P.matrix, s.M.T @ s.M)
        np.testing.assert_allclose(P.matrix, _explicit(s.J, s.M.T @ s.M), rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("weighted", [False, True])
def test_singular_configuration_is_bounded_and_reported(planar, weighted):
    """Outstretched arm: J = [[0, 0, 0], [3, 2, 1]] has rank 1; J⁺ stays bounded, the tick is singular."""
    dyn = Dynamics(planar)
    q = np.zeros(3)
    s = dyn.compute(q, np.zeros(3))
    np.testing.assert_allclose(s.J, [[0, 0, 0], [3, 2, 1]], atol=1e-12)
    eps = 1e-3
    P = weighted_pinv(s.J, s.M if weighted else None, eps=eps)
    assert P.singular and P.sigma_ratio < eps
    assert np.all(np.isfinite(P.matrix))
    Jt = s.J if not weighted else s.J @ np.linalg.inv(s.M).T
    smax = np.linalg.svd(Jt, compute_uv=False)[0]
    # σ/(σ² + λ²) ≤ 1/(2λ) with λ = eps σ_max at σ_min = 0, mapped back through F⁻ᵀ.
    bound = 1 / (2 * eps * smax) * (np.linalg.norm(np.linalg.inv(s.M), 2) if weighted else 1.0)
    assert np.linalg.norm(P.matrix, 2) <= bound
    # Along the direction J can still move (y), the inverse is exact.
    assert (s.J @ P.matrix)[1, 1] == pytest.approx(1.0, abs=1e-5)
    # Near (not at) the singularity: bounded by the same 1/(2λ) and continuous as q → 0.
    near = [weighted_pinv(dyn.compute(np.array([0.0, a, 0.0]), np.zeros(3)).J, None, eps=eps)
            for a in (1e-4, 1e-6, 1e-8)]
    assert all(p.singular for p in near)
    assert max(np.linalg.norm(p.matrix, 2) for p in near) <= 1 / (2 * eps * np.linalg.norm(s.J, 2)) * 1.01
    np.testing.assert_allclose(near[-1].matrix, weighted_pinv(s.J, None, eps=eps).matrix, atol=1e-3)


def test_damping_is_continuous_at_the_threshold(rng):
    """Just above and just below σ_min/σ_max = eps the two branches give the same matrix."""
    J = rng.normal(size=(2, 3))
    ratio = weighted_pinv(J).sigma_ratio
    above = weighted_pinv(J, eps=ratio * (1 - 1e-9))
    below = weighted_pinv(J, eps=ratio * (1 + 1e-9))
    assert not above.singular and below.singular
    np.testing.assert_allclose(above.matrix, below.matrix, rtol=1e-6)


def test_zero_jacobian():
    P = weighted_pinv(np.zeros((2, 3)))
    assert P.singular and np.all(P.matrix == 0) and P.matrix.shape == (3, 2)
