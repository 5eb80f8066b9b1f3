"""Small dense linear algebra for the tick's compiled kernels (matrices of a dozen rows or fewer).

numba's ``np.linalg`` allocates, copies to Fortran order and calls LAPACK on every call: 2–3 µs each
at 7×7, more than the arithmetic. These loops write into caller-owned arrays and allocate nothing.
Their references are numpy's own routines and :func:`qpctl.linalg.weighted_pinv` (numpy's SVD);
``tests/test_kernels.py`` holds each one against its reference.

* :func:`cholesky`, :func:`solve_lower`, :func:`solve_lower_t`, :func:`chol_solve` — A = L Lᵀ and
  the triangular solves, in place (column by column for matrix right-hand sides).
* :func:`gram_lower` — H = A Aᵀ (lower triangle) of a short-and-wide matrix, for the normal matrices of
  the reference velocity and of Ryu's W_b (rows packed once, then one dot product per entry).
* :func:`pinv_t` — the damped pseudo-inverse of a wide matrix given by its transpose, by one-sided
  (Hestenes) Jacobi SVD: accurate to rounding like LAPACK's SVD, without squaring the condition
  number as the normal equations would; with the variable damping of :mod:`qpctl.linalg`.
* :func:`normal_factor`, :func:`normal_solve`, :func:`pinv_t_normal`, :func:`pinv_t_apply` — the normal equations where a
  bound says they are certainly undamped: A⁺ itself, or A⁺ s for one vector s (the law's e_N), and
  :func:`pinv_t` where they are not.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

JACOBI_TOL = 1e-15  # columns p, q count as orthogonal when |b_p·b_q| ≤ tol ‖b_p‖‖b_q‖
JACOBI_SWEEPS = 40  # a 6-column matrix converges in 5–7 sweeps; this only bounds a pathological case


@njit(cache=True)
def cholesky(A: np.ndarray, L: np.ndarray) -> bool:
    """L (lower, upper triangle zeroed) with A = L Lᵀ, reading A's lower triangle; False if A is
    not (numerically) positive definite."""
    return cholesky_lead(A, L, A.shape[0])


@njit(cache=True)
def cholesky_lead(A: np.ndarray, L: np.ndarray, n: int) -> bool:
    """:func:`cholesky` of A's leading n × n block into L's (arrays at least that large)."""
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return False
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
        for i in range(j):
            L[i, j] = 0.0
    return True


@njit(cache=True)
def gram_lower(A: np.ndarray, k: int, H: np.ndarray) -> None:
    """H[i, j] = Σ_{c < k} A[i, c] A[j, c] for j ≤ i (the lower triangle of A Aᵀ over A's first k
    columns; the upper triangle is not written). A's rows are contiguous, so each entry is one dot
    product in column order (no fastmath: a reassociated, vectorised sum depends on the arrays'
    alignment, so two processes would round differently). 0.6 µs at n = 7, k = 33 against 1.6 µs for
    the rank-one updates of each row. H's first n rows and columns are written, n = A's rows (H may
    be larger: the QP's cost with its slack block)."""
    n = A.shape[0]
    for i in range(n):
        for j in range(i + 1):
            s = 0.0
            for c in range(k):
                s += A[i, c] * A[j, c]
            H[i, j] = s


@njit(cache=True)
def add_trace_ridge(A: np.ndarray, rel: float = 1e-9) -> None:
    """A ← A + rel·max(tr A, 1)·I: a ridge that keeps a sum of Jᵀ J positive definite."""
    tr = 0.0
    for i in range(A.shape[0]):
        tr += A[i, i]
    for i in range(A.shape[0]):
        A[i, i] += rel * max(tr, 1.0)


@njit(cache=True)
def solve_lower(L: np.ndarray, X: np.ndarray) -> None:
    """X ← L⁻¹ X for lower-triangular L; X is (n,) or (n, k)."""
    n = L.shape[0]
    if X.ndim == 1:
        for i in range(n):
            s = X[i]
            for k in range(i):
                s -= L[i, k] * X[k]
            X[i] = s / L[i, i]
    else:
        solve_lower_cols(L, X, X.shape[1])


@njit(cache=True)
def solve_lower_cols(L: np.ndarray, X: np.ndarray, cols: int) -> None:
    """:func:`solve_lower` on X's first ``cols`` columns (X 2-D)."""
    n = L.shape[0]
    for c in range(cols):
        for i in range(n):
            s = X[i, c]
            for k in range(i):
                s -= L[i, k] * X[k, c]
            X[i, c] = s / L[i, i]


@njit(cache=True)
def solve_lower_t(L: np.ndarray, X: np.ndarray) -> None:
    """X ← L⁻ᵀ X for lower-triangular L; X is (n,) or (n, k)."""
    n = L.shape[0]
    if X.ndim == 1:
        for i in range(n - 1, -1, -1):
            s = X[i]
            for k in range(i + 1, n):
                s -= L[k, i] * X[k]
            X[i] = s / L[i, i]
    else:
        solve_lower_t_cols(L, X, X.shape[1])


@njit(cache=True)
def solve_lower_t_cols(L: np.ndarray, X: np.ndarray, cols: int) -> None:
    """:func:`solve_lower_t` on X's first ``cols`` columns (X 2-D)."""
    n = L.shape[0]
    for c in range(cols):
        for i in range(n - 1, -1, -1):
            s = X[i, c]
            for k in range(i + 1, n):
                s -= L[k, i] * X[k, c]
            X[i, c] = s / L[i, i]


@njit(cache=True)
def chol_solve(L: np.ndarray, X: np.ndarray) -> None:
    """X ← A⁻¹ X with A = L Lᵀ."""
    solve_lower(L, X)
    solve_lower_t(L, X)


@njit(cache=True)
def chol_solve_cols(L: np.ndarray, X: np.ndarray, cols: int) -> None:
    """:func:`chol_solve` on X's first ``cols`` columns (X 2-D)."""
    solve_lower_cols(L, X, cols)
    solve_lower_t_cols(L, X, cols)


@njit(cache=True)
def pinv_t(B: np.ndarray, eps: float, V: np.ndarray, out: np.ndarray) -> tuple[bool, float]:
    """Damped pseudo-inverse A⁺ (n, m) of A (m, n, m ≤ n) given B = Aᵀ, which is overwritten.

    One-sided Jacobi rotates B's columns until they are orthogonal: B V = U Σ, so A = V Σ Uᵀ and
    A⁺ = U Σ⁺ Vᵀ = (B V) diag(1/σ²) Vᵀ. Below σ_min < eps σ_max each 1/σ² becomes 1/(σ² + λ²) with
    λ² = (1 − (σ_min/(eps σ_max))²)(eps σ_max)² — :func:`qpctl.linalg.weighted_pinv`'s variable damping.
    Returns (singular: the damping was used, σ_min/σ_max). V is an (m, m) scratch array.
    """
    n, m = B.shape
    for i in range(m):
        for j in range(m):
            V[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(JACOBI_SWEEPS):
        rotated = False
        for p in range(m - 1):
            for q in range(p + 1, m):
                alpha = beta = gamma = 0.0
                for i in range(n):
                    alpha += B[i, p] * B[i, p]
                    beta += B[i, q] * B[i, q]
                    gamma += B[i, p] * B[i, q]
                if abs(gamma) <= JACOBI_TOL * math.sqrt(alpha * beta):
                    continue
                rotated = True
                zeta = (beta - alpha) / (2.0 * gamma)
                t = math.copysign(1.0, zeta) / (abs(zeta) + math.sqrt(1.0 + zeta * zeta))
                c = 1.0 / math.sqrt(1.0 + t * t)
                s = c * t
                for i in range(n):
                    bp, bq = B[i, p], B[i, q]
                    B[i, p] = c * bp - s * bq
                    B[i, q] = s * bp + c * bq
                for i in range(m):
                    vp, vq = V[i, p], V[i, q]
                    V[i, p] = c * vp - s * vq
                    V[i, q] = s * vp + c * vq
        if not rotated:
            break
    smax2, smin2 = 0.0, np.inf
    for k in range(m):
        s2 = 0.0
        for i in range(n):
            s2 += B[i, k] * B[i, k]
        smax2 = max(smax2, s2)
        smin2 = min(smin2, s2)
    out[:, :] = 0.0
    if not smax2 > 0.0:
        return True, 0.0
    smax, smin = math.sqrt(smax2), math.sqrt(smin2)
    thresh = eps * smax
    lam2 = 0.0
    singular = smin < thresh
    if singular:
        lam2 = (1.0 - (smin / thresh) ** 2) * thresh * thresh
    for k in range(m):
        s2 = 0.0
        for i in range(n):
            s2 += B[i, k] * B[i, k]
        if s2 + lam2 <= 0.0:
            continue
        w = 1.0 / (s2 + lam2)
        for i in range(n):
            bik = B[i, k] * w
            for j in range(m):
                out[i, j] += bik * V[j, k]
    return singular, smin / smax


@njit(cache=True)
def normal_factor(B: np.ndarray, eps: float, V: np.ndarray, G: np.ndarray) -> tuple[bool, float]:
    """The normal equations of B = Aᵀ (n, m) where they are certainly undamped: G = BᵀB = A Aᵀ into
    ``G[:, :m]``, its Cholesky factor into V (m, m), and whether the lower bound √(1/(tr G · tr G⁻¹))
    ≤ σ_min/σ_max (tr G ≥ λ_max, tr G⁻¹ ≥ 1/λ_min) is at least ``eps`` — then :func:`pinv_t` would not
    damp. Returns (that, the bound); (False, 0) where G is not positive definite. G is (m, m + 2):
    its column m is scratch."""
    n, m = B.shape
    tr = 0.0
    for p in range(m):
        for q in range(p + 1):
            s = 0.0
            for i in range(n):
                s += B[i, p] * B[i, q]
            G[p, q] = G[q, p] = s
        tr += G[p, p]
    if not (tr > 0.0 and cholesky(G, V)):
        return False, 0.0
    # tr G⁻¹ = ‖L⁻¹‖_F², column by column of L⁻¹ (forward substitution on the unit vectors)
    tr_inv = 0.0
    for j in range(m):
        for i in range(m):
            s = 1.0 if i == j else 0.0
            for k in range(j, i):
                s -= V[i, k] * G[k, m]
            G[i, m] = s / V[i, i] if i >= j else 0.0
            if i >= j:
                tr_inv += G[i, m] * G[i, m]
    bound = math.sqrt(1.0 / (tr * tr_inv))
    return bound >= eps, bound


@njit(cache=True, inline="always")
def normal_solve(V: np.ndarray, G: np.ndarray, m: int) -> None:
    """G[:, m + 1] ← (V Vᵀ)⁻¹ G[:, m + 1]: V an m × m Cholesky factor (of the normal matrix in G's first
    m columns, :func:`normal_factor`), G's column m + 1 the right-hand side, solved in place."""
    for j in range(m):
        s = G[j, m + 1]
        for k in range(j):
            s -= V[j, k] * G[k, m + 1]
        G[j, m + 1] = s / V[j, j]
    for j in range(m - 1, -1, -1):
        s = G[j, m + 1]
        for k in range(j + 1, m):
            s -= V[k, j] * G[k, m + 1]
        G[j, m + 1] = s / V[j, j]


@njit(cache=True)
def pinv_t_normal(B: np.ndarray, eps: float, V: np.ndarray, out: np.ndarray,
                  G: np.ndarray) -> tuple[bool, float]:
    """:func:`pinv_t`, by the normal equations where that is certainly undamped (:func:`normal_factor`):
    A⁺ = B (BᵀB)⁻¹ by Cholesky; otherwise, and where G is not positive definite, :func:`pinv_t` itself.
    The bound is loose by at most a factor m, so the Jacobi SVD runs only within a factor m of the
    damping threshold. Returns (singular, that lower bound) on the fast path, :func:`pinv_t`'s pair
    otherwise; B is kept on the fast path. G is an (m, m + 2) scratch (the Gram matrix, then two
    vectors): nothing is allocated."""
    n, m = B.shape
    ok, bound = normal_factor(B, eps, V, G)
    if not ok:
        return pinv_t(B, eps, V, out)
    # out = B G⁻¹, row by row: G y = B[i, :]
    for i in range(n):
        for j in range(m):
            G[j, m + 1] = B[i, j]
        normal_solve(V, G, m)
        for j in range(m):
            out[i, j] = G[j, m + 1]
    return False, bound


@njit(cache=True)
def pinv_t_apply(B: np.ndarray, eps: float, V: np.ndarray, G: np.ndarray, s: np.ndarray,
                 z: np.ndarray) -> bool:
    """z (n,) = A⁺ s for s (m,), B = Aᵀ (n, m), where the normal equations are certainly undamped
    (:func:`normal_factor`): z = B (BᵀB)⁻¹ s — one right-hand side, not A⁺'s m columns. Returns False
    (z untouched, B kept, G's Gram matrix and V its factor when positive definite) where they are
    not: then form A⁺ with :func:`pinv_t`, which damps."""
    n, m = B.shape
    ok, _bound = normal_factor(B, eps, V, G)
    if not ok:
        return False
    for j in range(m):
        G[j, m + 1] = s[j]
    normal_solve(V, G, m)
    for i in range(n):
        acc = 0.0
        for j in range(m):
            acc += B[i, j] * G[j, m + 1]
        z[i] = acc
    return True
