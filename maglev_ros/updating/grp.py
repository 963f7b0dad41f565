"""Grey relational projection (GRP, 000 Sec. 4.3, ref. [34]) to pick one Pareto solution.

All objectives are costs (smaller is better). Steps (the paper's equations were lost; this is the
standard GRP of e.g. Lu et al.): min-max normalise each objective over the archive; positive ideal
= best (0) and negative ideal = worst (1) per objective; grey relational coefficients
xi+/-_ij = (dmin + rho dmax) / (d+/-_ij + rho dmax) with d the absolute distance to the ideal and
rho = 0.5 the resolution coefficient; projections P+/-_i = sum_j xi+/-_ij w_j^2 / |w| (the projection
of the weighted coefficient vector on the ideal vector w); superiority S_i = P+_i / (P+_i + P-_i).
The solution with the highest superiority is chosen. Hand-written: ~20 lines, no library has it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from maglev_ros.errors import UserError


@dataclass(frozen=True)
class GrpResult:
    index: int
    superiority: np.ndarray

    def to_dict(self) -> dict:
        return {"index": int(self.index), "superiority": self.superiority.tolist()}


def _coeff(d: np.ndarray, rho: float) -> np.ndarray:
    dmin, dmax = float(d.min()), float(d.max())
    if dmax <= 0:
        return np.ones_like(d)
    return (dmin + rho * dmax) / (d + rho * dmax)


def grey_relational_projection(objectives, weights=None, rho: float = 0.5) -> GrpResult:
    f = np.atleast_2d(np.asarray(objectives, dtype=float))
    if f.size == 0 or not np.all(np.isfinite(f)):
        raise UserError("grey relational projection: expected a non-empty finite objective table")
    m = f.shape[1]
    w = np.full(m, 1.0 / m) if weights is None else np.asarray(weights, dtype=float)
    lo, hi = f.min(axis=0), f.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    z = (f - lo) / span
    xi_p = _coeff(np.abs(z - 0.0), rho)
    xi_n = _coeff(np.abs(z - 1.0), rho)
    wn = np.linalg.norm(w)
    p_pos = xi_p @ (w ** 2) / wn
    p_neg = xi_n @ (w ** 2) / wn
    s = p_pos / (p_pos + p_neg)
    return GrpResult(int(np.argmax(s)), s)
