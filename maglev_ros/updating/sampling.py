"""Optimal Latin hypercube sampling (000 Sec. 5.1.1, ref. [35]).

"Optimal" here: scipy's ``qmc.LatinHypercube(optimization="random-cd")`` (centred-discrepancy
optimised LHS) for ``n_candidates`` seeds, then the candidate with the largest minimum pairwise
distance (maximin) is kept. scipy has no maximin option itself; this selection step is ours.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.distance import pdist
from scipy.stats import qmc

from maglev_ros.errors import UserError


def maximin_distance(u: np.ndarray) -> float:
    return float(pdist(u).min()) if len(u) > 1 else float("inf")


def optimal_lhs(n: int, dim: int, seed: int | None = 0, n_candidates: int = 8) -> np.ndarray:
    """(n, dim) points in [0, 1)^dim: one point per stratum in every dimension, maximin-selected."""
    if n < 2 or dim < 1:
        raise UserError(f"optimal_lhs: expected n >= 2 and dim >= 1, got n={n}, dim={dim}")
    rng = np.random.default_rng(seed)
    best, best_d = None, -1.0
    for _ in range(max(1, n_candidates)):
        s = qmc.LatinHypercube(d=dim, optimization="random-cd", seed=rng).random(n)
        d = maximin_distance(s)
        if d > best_d:
            best, best_d = s, d
    return best
