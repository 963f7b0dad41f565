"""Identifiability from the whitened sensitivity (Jacobian) at the optimum.

J[i, j] = d(residual_i / sigma_i) / d theta_j with theta = log(p / p_nominal). The Fisher information
is F = J^T J. Its SVD J = U S V^T gives the directions the data determine (large singular values)
and ridges (singular value below ``rel_tol`` times the largest): moving along a ridge direction
changes no prediction, e.g. the common scale of E and rho (and kb) leaves every frequency and mode
shape unchanged, so only E/rho (EI/m) and kb/rho are determined by modes alone.

A log-linear combination c^T theta (a named product of powers, e.g. E^1 rho^-1 = "E/rho") is
identifiable when c has no component along a ridge; its standard deviation is sqrt(c^T F^+ c)
(pseudo-inverse: the Cramer-Rao bound of an estimable function, first order, measurement noise as
given by sigma). A single parameter is identifiable when its unit vector is estimable and its
relative std is below ``max_rel_std``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np


@dataclass(frozen=True)
class Combination:
    expression: str
    exponents: tuple[float, ...]
    value: float
    std: float
    identifiable: bool

    def to_dict(self) -> dict:
        return {"expression": self.expression, "value": float(self.value), "std": float(self.std)}


@dataclass(frozen=True)
class Identifiability:
    names: tuple[str, ...]
    singular_values: tuple[float, ...]
    ridge_directions: tuple[tuple[float, ...], ...]   # unit vectors in theta space
    theta_cov: np.ndarray                             # pseudo-inverse of the Fisher information
    param_std: tuple[float, ...]                      # NaN where not identifiable
    identifiable: tuple[bool, ...]
    combinations: tuple[Combination, ...]

    def to_dict(self) -> dict:
        return {"names": list(self.names), "singular_values": list(self.singular_values),
                "ridge_directions": [list(r) for r in self.ridge_directions],
                "param_std": [None if not np.isfinite(s) else float(s) for s in self.param_std],
                "identifiable": list(self.identifiable),
                "combinations": [c.to_dict() | {"identifiable": c.identifiable} for c in self.combinations]}


def jacobian(func: Callable[[np.ndarray], np.ndarray], theta: np.ndarray, step: float = 1e-4,
             f0: np.ndarray | None = None, central: bool = True) -> tuple[np.ndarray, np.ndarray]:
    theta = np.asarray(theta, dtype=float)
    f0 = np.asarray(func(theta), dtype=float) if f0 is None else f0
    J = np.empty((f0.size, theta.size))
    for j in range(theta.size):
        e = np.zeros_like(theta)
        e[j] = step
        if central:
            J[:, j] = (np.asarray(func(theta + e)) - np.asarray(func(theta - e))) / (2 * step)
        else:
            J[:, j] = (np.asarray(func(theta + e)) - f0) / step
    return J, f0


# a parameter combination is called identifiable when the data determine it to 1 % (1 sigma): the
# accuracy the updating is held to for combinations (2 %, at 2 sigma). With the single gains' 2.5 % a
# weak magnet combination with std 2.3 % was reported and came out 2.8 % off
COMBINATION_MAX_REL_STD = 0.01


def analyse(J_white: np.ndarray, names: Sequence[str], values: np.ndarray,
            combinations: Sequence[tuple[str, Sequence[float]]] = (), rel_tol: float = 1e-6,
            max_rel_std: float = 0.1, fixed_unidentifiable: Sequence[str] = (),
            estimable_tol: float = 1e-3, combination_max_rel_std: float = COMBINATION_MAX_REL_STD
            ) -> Identifiability:
    """``J_white``: whitened Jacobian w.r.t. log-parameters; ``values``: parameter values at the optimum.
    ``combinations``: (expression, exponents over ``names``) candidates to report, identifiable when
    their relative std <= ``combination_max_rel_std``."""
    p = len(names)
    # thin SVD (a full U of a long residual vector is n x n: 12 GB for two 10 s passes); zero rows
    # pad a short J so that Vt still spans the whole parameter space (null space included)
    Jw = np.asarray(J_white, dtype=float)
    if Jw.shape[0] < p:
        Jw = np.vstack([Jw, np.zeros((p - Jw.shape[0], p))])
    _, s, Vt = np.linalg.svd(Jw, full_matrices=False)
    s_full = np.zeros(p)
    s_full[: s.size] = s
    smax = s_full.max() if s_full.size else 0.0
    ridge = [Vt[k] for k in range(p) if s_full[k] <= rel_tol * max(smax, 1e-300)]
    N = np.array(ridge).reshape(len(ridge), p)
    keep = s_full > rel_tol * max(smax, 1e-300)
    inv = np.zeros(p)
    inv[keep] = 1.0 / s_full[keep] ** 2
    cov = (Vt.T * inv) @ Vt

    def estimable(c):
        c = np.asarray(c, dtype=float)
        return N.size == 0 or np.linalg.norm(N @ c) <= estimable_tol * max(np.linalg.norm(c), 1e-300)

    stds, ident = [], []
    for j in range(p):
        e = np.zeros(p)
        e[j] = 1.0
        ok = estimable(e) and names[j] not in fixed_unidentifiable
        rel = float(np.sqrt(max(e @ cov @ e, 0.0))) if ok else np.nan
        ok = ok and rel <= max_rel_std
        stds.append(rel * float(values[j]) if np.isfinite(rel) else np.nan)
        ident.append(bool(ok))
    combos = []
    for expr, c in combinations:
        c = np.asarray(c, dtype=float)
        val = float(np.prod(np.asarray(values, dtype=float) ** c))
        if estimable(c):
            rel = float(np.sqrt(max(c @ cov @ c, 0.0)))
            combos.append(Combination(expr, tuple(map(float, c)), val, rel * abs(val), rel <= combination_max_rel_std))
        else:
            combos.append(Combination(expr, tuple(map(float, c)), val, float("nan"), False))
    return Identifiability(tuple(names), tuple(map(float, s_full)), tuple(tuple(map(float, r)) for r in N),
                           cov, tuple(stds), tuple(ident), tuple(combos))
