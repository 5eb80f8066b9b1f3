"""Weighted, damped pseudo-inverses (paper eq. 5–6)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class PseudoInverse(NamedTuple):
    """J_W⁺ with what the SVD said about J."""

    matrix: np.ndarray  # (n, m)
    singular: bool  # σ_min/σ_max of the weighted Jacobian fell below eps: damping was used
    sigma_ratio: float  # σ_min/σ_max of the weighted Jacobian


def weighted_pinv(J: np.ndarray, factor: np.ndarray | None = None, *, eps: float = 1e-3) -> PseudoInverse:
    """Weighted pseudo-inverse J_W⁺ = W⁻¹Jᵀ(J W⁻¹ Jᵀ)⁻¹ (eq. 6), computed by SVD and damped near singularities.

    The weight is given by a factor F with W = F Fᵀ (for W = MᵀM with M symmetric, F = M; for
    W = I, ``factor=None``). With J̃ = J F⁻ᵀ = U Σ Vᵀ, J_W⁺ = F⁻ᵀ V Σ⁺ Uᵀ. Away from singularities
    (σ_min ≥ eps σ_max) this is exact and satisfies the four conditions of eq. (5) in the metric W:
    J J⁺ J = J, J⁺ J J⁺ = J⁺, (J J⁺)ᵀ = J J⁺, W J⁺ J symmetric, and J J⁺ = I. Below, σ_i is replaced by
    σ_i/(σ_i² + λ²) with λ² = (1 − (σ_min/(eps σ_max))²)(eps σ_max)² (variable damping, Maciejewski),
    so J_W⁺ stays bounded by 1/(2λ) and changes continuously.
    """
    if factor is None:
        Jt = J
    else:
        Jt = np.linalg.solve(factor, J.T).T  # J F⁻ᵀ
    U, s, Vt = np.linalg.svd(Jt, full_matrices=False)
    smax = float(s[0]) if s.size else 0.0
    if smax <= 0.0:
        n, m = J.shape[1], J.shape[0]
        return PseudoInverse(np.zeros((n, m)), True, 0.0)
    ratio = float(s[-1] / smax)
    thresh = eps * smax
    if s[-1] >= thresh:
        sinv = 1.0 / s
        singular = False
    else:
        lam2 = (1.0 - (s[-1] / thresh) ** 2) * thresh**2
        sinv = s / (s * s + lam2)
        singular = True
    Jt_pinv = (Vt.T * sinv) @ U.T
    if factor is not None:
        Jt_pinv = np.linalg.solve(factor.T, Jt_pinv)  # F⁻ᵀ J̃⁺
    return PseudoInverse(Jt_pinv, singular, ratio)
