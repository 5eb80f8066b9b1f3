"""Hsu–Hauser–Sastry's law (baseline ``hsu``), the paper's "conventional unweighted algorithm".

The same structure as :mod:`baselines.paper` with the Moore–Penrose pseudo-inverse everywhere
(W = W_b = I) and no torque term in the null space:

    q̈ = J⁺ a + (I − J⁺J) K_N e_N,   e_N = (I − J⁺J)(g − q̇),   τ = M q̈ + N
"""

from __future__ import annotations

from baselines.paper import PaperController


class HsuController(PaperController):
    """Unweighted resolved-acceleration control with null-space velocity tracking (Hsu et al. 1989)."""

    kind = "hsu"
    weighted = False
