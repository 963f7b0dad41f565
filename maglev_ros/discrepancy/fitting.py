"""Joint fitting of calibrated parameters and extension parameters on band-amplitude residuals.

Calibrated parameters (log-factors of E, kb, kp, kv against the design block) are fitted by
scipy.optimize.least_squares (finite-difference Jacobian, weak Gaussian prior of 0.5 in log-factor
so that weakly observable ones stay near the design). An extension with one parameter p is fitted
jointly: p by a bounded scalar search (scipy.optimize.minimize_scalar), and for each p the
calibrated parameters re-fitted by one Gauss-Newton step on the Jacobian of the base fit
(variable projection, linearised in the calibrated parameters), so a change that merely mimics a
calibrated parameter gains nothing. Multi-parameter extensions that need no simulation (sensor
errors) are fitted by least_squares directly.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, minimize_scalar

from .catalogue import Hypothesis
from .evaluate import RecData, residual_vector
from .model import CAL_PARAMS, ModelSpec

PRIOR_SIGMA = 0.5
CAL_LO = np.array([-0.7, -2.5, -0.5, -0.7])
CAL_HI = np.array([0.7, 2.5, 0.5, 0.7])


@dataclass
class BaseFit:
    spec: ModelSpec
    theta: np.ndarray
    jac: np.ndarray          # data rows only
    r0: np.ndarray
    n_sims: int


def _with_cal(spec: ModelSpec, th) -> ModelSpec:
    return spec.with_(cal=tuple(float(x) for x in th))


def fit_base(spec: ModelSpec, rds: list[RecData], max_nfev: int = 6) -> BaseFit:
    n_data = [0]
    calls = [0]

    def fun(th):
        calls[0] += 1
        r = residual_vector(_with_cal(spec, th), rds)
        n_data[0] = r.size
        return np.concatenate([r, 0.02 * th / PRIOR_SIGMA])
    x0 = np.clip(np.array(spec.cal, float), CAL_LO, CAL_HI)
    res = least_squares(fun, x0, bounds=(CAL_LO, CAL_HI), diff_step=0.03, max_nfev=max_nfev,
                        x_scale=1.0, ftol=1e-4, xtol=1e-4)
    th = res.x
    sp = _with_cal(spec, th)
    r0 = residual_vector(sp, rds)
    jac = res.jac[:r0.size]
    return BaseFit(sp, th, np.asarray(jac), r0, calls[0])


def _project(base: BaseFit, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Re-fit calibrated parameters linearly: min ||r + J d||^2 + ||0.02 (th + d)/sigma||^2."""
    J = base.jac
    lam = (0.02 / PRIOR_SIGMA) ** 2
    A = J.T @ J + lam * np.eye(J.shape[1])
    d = -np.linalg.solve(A, J.T @ r + lam * base.theta)
    d = np.clip(base.theta + d, CAL_LO, CAL_HI) - base.theta
    return r + J @ d, d


@dataclass
class HypFit:
    hyp: Hypothesis
    params: np.ndarray
    cal_delta: np.ndarray
    rss: float
    spec: ModelSpec
    n_sims: int

    @property
    def k(self) -> int:
        return len(self.params)


def screen(base: BaseFit, hyp: Hypothesis, rds: list[RecData]) -> float:
    """RSS at the trial value with calibrated parameters projected (1 simulation)."""
    if hyp.effect == "sensor_error":
        return fit_sensor(base, hyp, rds).rss
    sp = hyp.apply(base.spec, np.array(hyp.trial))
    r, _ = _project(base, residual_vector(sp, rds))
    return float(r @ r)


def fit_1d(base: BaseFit, hyp: Hypothesis, rds: list[RecData], maxiter: int = 9) -> HypFit:
    cache = {}

    def rss(p):
        sp = hyp.apply(base.spec, np.array([p]))
        r, d = _project(base, residual_vector(sp, rds))
        cache[p] = (float(r @ r), d)
        return cache[p][0]
    lo, hi = hyp.lower[0], hyp.upper[0]
    res = minimize_scalar(rss, bounds=(lo, hi), method="bounded", options={"maxiter": maxiter, "xatol": 1e-3 * (hi - lo)})
    p = min(cache, key=lambda q: cache[q][0])
    rs, d = cache[p]
    sp = hyp.apply(base.spec, np.array([p]))
    sp = sp.with_(cal=tuple(float(x) for x in base.theta + d))
    return HypFit(hyp, np.array([p]), d, rs, sp, len(cache))


def fit_sensor(base: BaseFit, hyp: Hypothesis, rds: list[RecData]) -> HypFit:
    ch = hyp.location["channels"][0]
    # scale of the offset/drift parameters from the channel's measured spread
    sig = np.concatenate([rd.rec.channels[ch].values for rd in rds])
    s_off = float(np.std(sig)) or 1.0
    tspan = max(rd.rec.t1_s - rd.rec.t0_s for rd in rds)

    def fun(z):
        p = np.array([z[0], z[1] * s_off, z[2] * s_off / tspan])
        return residual_vector(hyp.apply(base.spec, p), rds)
    res = least_squares(fun, np.zeros(3), diff_step=1e-3, max_nfev=30, bounds=([-2, -50, -50], [2, 50, 50]))
    p = np.array([res.x[0], res.x[1] * s_off, res.x[2] * s_off / tspan])
    sp = hyp.apply(base.spec, p)
    r = residual_vector(sp, rds)
    return HypFit(hyp, p, np.zeros_like(base.theta), float(r @ r), sp, 0)


def fit_hypothesis(base: BaseFit, hyp: Hypothesis, rds: list[RecData]) -> HypFit:
    if hyp.effect == "sensor_error":
        return fit_sensor(base, hyp, rds)
    return fit_1d(base, hyp, rds)


def bic(rss: float, n: int, k: int) -> float:
    """BIC of a Gaussian residual with unknown variance; n = effective number of residuals."""
    return n * math.log(max(rss, 1e-300) / n) + k * math.log(n)
