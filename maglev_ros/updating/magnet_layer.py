"""Magnetic-force layer (000 Sec. 4.2.2, Eqs. 26-27): controller gains kp, kv, ka from the measured
electromagnet accelerations of vehicle passes, on the coupled twin with the UPDATED guideway.

Model: ``twin.coupling.simulate_pass`` driven by the pass's measured speed (t, v), its start position
and an irregularity r(x) reconstructed from the pass (see ``irregularity_from_pass``); the predicted
magnet accelerations are compared with the measured ones after ``skip_s`` (start transient).
Objectives (MOPSO; 000's Eq. 27 text was lost, these follow its description "simulated vs measured
acceleration, their averages, number of moments"): f1 = NRMSE = rms(a_sim - a_meas) / rms(a_meas),
f2 = 1 - Pearson correlation of a_sim and a_meas (pooled over magnets and passes).

One coupled simulation costs ~0.2 s per simulated second, so the global search runs on an Elman
surrogate of (f1, f2) trained on optimal-LHS samples (``use_surrogate``, default), MOPSO + GRP pick a
point, and a local least-squares fit of the acceleration time series on the DIRECT model polishes it.

Identifiability: with F = C (I/gap)^2 and C fixed by the static load at (I0, g0), the linearised
force only depends on kp/I0, kv/I0, ka/I0, and the full nonlinear model is invariant under a common
scale of (kp, kv, ka, I0) (C scales as 1/I0^2): the gains are confounded with the static current and
the magnet constant. The Jacobian w.r.t. (kp, kv, ka, I0) exposes this ridge; the combinations
kp/I0, kv/I0, ka/I0 are reported. With ``fix_static_current`` (default) I0 is taken as known from the
design (data sheet) and the gains are reported as identifiable GIVEN I0; otherwise they are flagged
not identifiable. Standard deviations: Fisher information from the Jacobian at the optimum, with the
residual rms as noise level and the sample count reduced to an effective count by the residual's
integrated autocorrelation time (first order; model error is counted as noise).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.optimize import least_squares

from maglev_ros.errors import UserError
from maglev_ros.twin.coupling import simulate_pass
from maglev_ros.twin.design import TwinConfig, with_levitation
from maglev_ros.updating.grp import grey_relational_projection
from maglev_ros.updating.identifiability import Identifiability, analyse, jacobian
from maglev_ros.updating.mopso import MOPSO, ParetoResult
from maglev_ros.updating.parameters import MAGNET_PARAMS, magnet_space
from maglev_ros.updating.sampling import optimal_lhs


def nrmse(pred: np.ndarray, meas: np.ndarray) -> float:
    d = float(np.sqrt(np.mean(np.asarray(meas) ** 2)))
    return float(np.sqrt(np.mean((np.asarray(pred) - np.asarray(meas)) ** 2)) / d) if d > 0 else float("inf")


def corr(pred: np.ndarray, meas: np.ndarray) -> float:
    a, b = np.ravel(pred) - np.mean(pred), np.ravel(meas) - np.mean(meas)
    den = float(np.sqrt((a @ a) * (b @ b)))
    return float(a @ b / den) if den > 0 else 0.0


@dataclass(frozen=True)
class PassEvidence:
    """One pass: measured magnet accelerations at ``time_s`` (seconds from the window start), magnets
    (1-based), speed profile, reference position at time 0 and the irregularity (x, r)."""
    time_s: np.ndarray
    accel_mps2: np.ndarray            # (n, len(magnets))
    magnets: tuple[int, ...]
    speed_time_s: np.ndarray
    speed_mps: np.ndarray
    start_position_m: float
    irregularity_x_m: np.ndarray
    irregularity_m: np.ndarray
    label: str = ""

    @property
    def duration_s(self) -> float:
        return float(self.time_s[-1])


class MagnetModel:
    """Coupled twin predictions of the measured magnet accelerations for given gains."""

    def __init__(self, config: TwinConfig, line, evidence: PassEvidence, skip_s: float = 0.3,
                 fs_out_hz: float | None = None):
        self.config, self.line, self.ev = config, line, evidence
        t = np.asarray(evidence.time_s, dtype=float)
        self.fs = fs_out_hz or float(round(1.0 / np.median(np.diff(t))))
        self.keep = t >= t[0] + skip_s
        if self.keep.sum() < 10:
            raise UserError(f"pass {evidence.label}: too short after skipping {skip_s} s of start transient")
        self.measured = np.asarray(evidence.accel_mps2, dtype=float)[self.keep]
        self.n_evaluations = 0

    def predict(self, values: Sequence[float], static_current_a: float | None = None) -> np.ndarray:
        kw = dict(zip(MAGNET_PARAMS, map(float, values)))
        if static_current_a is not None:
            kw["static_current_a"] = float(static_current_a)
        cfg = with_levitation(self.config, **kw)
        ev = self.ev
        res = simulate_pass(cfg, self.line, speed_mps=(ev.speed_time_s, ev.speed_mps),
                            irregularity=(ev.irregularity_x_m, ev.irregularity_m),
                            duration_s=float(ev.time_s[-1]) + 2.0 / self.fs, fs_out_hz=self.fs,
                            start_position_m=ev.start_position_m)
        self.n_evaluations += 1
        idx = [m - 1 for m in ev.magnets]
        t = np.asarray(ev.time_s)[self.keep]
        return np.stack([np.interp(t, res.time_s, res.magnet_accel_mps2[:, k]) for k in idx], axis=1)


def _ess_factor(r: np.ndarray) -> float:
    """n / n_eff = integrated autocorrelation time of the residual (up to its first zero crossing)."""
    r = np.asarray(r, dtype=float).ravel() - np.mean(r)
    n = r.size
    if n < 8 or not np.any(r):
        return 1.0
    f = np.fft.rfft(r, 2 * n)
    ac = np.fft.irfft(f * np.conj(f))[:n]
    ac /= ac[0]
    neg = np.flatnonzero(ac <= 0)
    m = neg[0] if neg.size else n
    return float(max(1.0, 1.0 + 2.0 * np.sum(ac[1:m])))


@dataclass(frozen=True)
class MagnetUpdate:
    names: tuple[str, ...]
    nominal: tuple[float, ...]
    values: tuple[float, ...]
    std: tuple[float | None, ...]
    identifiable: tuple[bool, ...]
    static_current_a: float
    identifiability: Identifiability
    nrmse_nominal: float
    nrmse_updated: float
    pareto: ParetoResult
    grp_index: int
    n_model_evaluations: int
    wall_time_s: float
    surrogate_score: dict | None = None

    def value(self, name: str) -> float:
        return self.values[self.names.index(name)]

    def to_dict(self) -> dict:
        return {"names": list(self.names), "nominal": list(self.nominal), "values": list(self.values),
                "std": list(self.std), "identifiable": list(self.identifiable),
                "static_current_a": self.static_current_a, "identifiability": self.identifiability.to_dict(),
                "magnet_accel_nrmse": {"nominal": self.nrmse_nominal, "updated": self.nrmse_updated},
                "pareto": self.pareto.to_dict(), "grp_index": self.grp_index,
                "n_model_evaluations": self.n_model_evaluations, "wall_time_s": self.wall_time_s,
                "surrogate_score": self.surrogate_score}


MAGNET_COMBINATIONS = (("kp/I0", (1.0, 0.0, 0.0, -1.0)), ("kv/I0", (0.0, 1.0, 0.0, -1.0)),
                       ("ka/I0", (0.0, 0.0, 1.0, -1.0)))


class MagnetLayer:
    """fit(config_with_updated_guideway, line, passes) -> MagnetUpdate."""

    def __init__(self, rel_range: float = 0.45, use_surrogate: bool = True, n_samples: int = 60,
                 n_particles: int = 50, archive_size: int = 40, n_iterations: int = 100, n_grid: int = 7,
                 polish_max_nfev: int = 40, skip_s: float = 0.3, fix_static_current: bool = True,
                 seed: int = 0, surrogate_kwargs: dict | None = None):
        self.rel_range, self.use_surrogate, self.n_samples = rel_range, bool(use_surrogate), int(n_samples)
        self.mopso = dict(n_particles=n_particles, archive_size=archive_size, n_iterations=n_iterations,
                          n_grid=n_grid, inertia=0.5, c1=1.0, c2=2.0, mutation_rate=0.1, seed=seed)
        self.polish_max_nfev, self.skip_s = int(polish_max_nfev), float(skip_s)
        self.fix_static_current, self.seed = bool(fix_static_current), seed
        self.surrogate_kwargs = surrogate_kwargs or {}

    def fit(self, config: TwinConfig, line, passes: Sequence[PassEvidence]) -> MagnetUpdate:
        t_start = time.perf_counter()
        if not passes:
            raise UserError("magnet layer: expected at least one pass with magnet accelerations")
        space = magnet_space(config, self.rel_range)
        models = [MagnetModel(config, line, p, self.skip_s) for p in passes]
        meas = np.concatenate([m.measured.ravel() for m in models])

        def predict_all(values, i0=None):
            return np.concatenate([m.predict(values, i0).ravel() for m in models])

        def objectives(values):
            p = predict_all(values)
            return np.array([nrmse(p, meas), 1.0 - corr(p, meas)])

        lo, hi = space.theta_bounds
        surrogate_score = None
        if self.use_surrogate:
            from maglev_ros.updating.surrogate import train_and_score
            U = optimal_lhs(self.n_samples, space.dim, seed=self.seed)
            Xs = np.array([space.from_unit(u) for u in U])
            Y = np.array([objectives(x) for x in Xs])
            Y = np.maximum(Y, 1e-9)
            kw = dict(hidden=16, log_outputs=True) | self.surrogate_kwargs
            sur, sc = train_and_score(Xs, Y, seed=self.seed, **kw)
            surrogate_score = {"n_samples": self.n_samples, "outputs": "nrmse, 1-corr", **sc.to_dict()}
            best_sample = space.to_theta(Xs[int(np.argmin(Y[:, 0]))])

            def batch(theta):
                return sur.predict(space.from_theta(theta))
        else:
            best_sample = np.zeros(space.dim)

            def batch(theta):
                return np.array([objectives(v) for v in space.from_theta(theta)])
        pareto = MOPSO(**self.mopso).minimize(batch, lo, hi, x0=np.vstack([np.zeros(space.dim), best_sample]))
        grp = grey_relational_projection(pareto.f)
        theta0 = pareto.x[grp.index]

        # ---- direct polish: least squares on the acceleration time series ----------------------
        def residual(theta):
            return predict_all(space.from_theta(theta)) - meas
        sol = least_squares(residual, theta0, bounds=(lo, hi), diff_step=2e-3, x_scale=0.1,
                            xtol=1e-6, ftol=1e-8, max_nfev=self.polish_max_nfev)
        theta = sol.x
        values = space.clip(space.from_theta(theta))
        r_opt = sol.fun
        sigma = float(np.sqrt(np.mean(r_opt ** 2)))
        scale = np.sqrt(_ess_factor(r_opt))      # inflate for correlated residuals
        i0 = config.levitation.static_current_a

        def res_full(th4):
            v = space.from_theta(th4[:3])
            return predict_all(v, i0 * np.exp(th4[3]))
        J, _ = jacobian(res_full, np.concatenate([theta, [0.0]]), step=2e-3, f0=r_opt + meas, central=False)
        Jw = J / (sigma * scale)
        names4 = space.names + ("static_current_a",)
        vals4 = np.concatenate([values, [i0]])
        ident4 = analyse(Jw, names4, vals4, MAGNET_COMBINATIONS, rel_tol=1e-2, max_rel_std=0.1, estimable_tol=2e-2)
        if self.fix_static_current:
            ident3 = analyse(Jw[:, :3], space.names, values, (), rel_tol=1e-4, max_rel_std=0.1)
            std = tuple(None if not np.isfinite(s) else float(s) for s in ident3.param_std)
            identifiable = ident3.identifiable
        else:
            std = tuple(None for _ in space.names)
            identifiable = tuple(False for _ in space.names)
        nominal_pred = predict_all(space.nominal)
        return MagnetUpdate(
            names=space.names, nominal=tuple(map(float, space.nominal)), values=tuple(map(float, values)),
            std=std, identifiable=tuple(map(bool, identifiable)), static_current_a=float(i0),
            identifiability=ident4, nrmse_nominal=nrmse(nominal_pred, meas),
            nrmse_updated=nrmse(r_opt + meas, meas),
            pareto=ParetoResult(space.from_theta(pareto.x), pareto.f, pareto.n_evaluations, pareto.n_iterations),
            grp_index=grp.index, n_model_evaluations=sum(m.n_evaluations for m in models),
            wall_time_s=time.perf_counter() - t_start, surrogate_score=surrogate_score)


def _highpass_fft(x: np.ndarray, fs_hz: float, fc_hz: float) -> tuple[np.ndarray, np.ndarray]:
    n = x.shape[0]
    nfft = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfftfreq(nfft, 1.0 / fs_hz)
    h = (f / fc_hz) ** 4 / (1.0 + (f / fc_hz) ** 4)          # zero-phase, 2nd-order Butterworth magnitude^2
    X = np.fft.rfft(x - x.mean(axis=0), nfft, axis=0)
    return X, f, h, nfft


def irregularity_from_signals(time_s: np.ndarray, accel_mps2: np.ndarray, gap_m: np.ndarray,
                              position_m: np.ndarray, magnet_offsets_m: Sequence[float], nominal_gap_m: float,
                              detrend_order: int = 3, spacing_m: float | None = None,
                              modal=None, magnet_force_n: np.ndarray | None = None,
                              deflection_m: np.ndarray | None = None,
                              lowpass_hz: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Simple inertial-reference reconstruction of the irregularity r(x) from one pass.

    Rail-underside elevation at magnet k: y_k = (gap_k - g0) + z_k (contract: gap = g0 + y - z_m), z_k
    the double integral of the magnet acceleration (trapezoid rule). With ``modal`` (the
    twin's ``ModalBasis``) and the static magnet forces, the quasi-static girder deflection under the
    vehicle, w_k = sum_j Phi(x_k) Omega^-2 Phi(x_j)^T (-F_j), is subtracted (unloaded profile, so the
    coupled twin does not count the deflection twice). ``deflection_m`` (n, m), when given instead, is
    the girder deflection at the magnets (e.g. the twin's prediction, dynamic part included) and is
    subtracted as it is. ``lowpass_hz``: zero-phase 4th-order Butterworth low-pass of each magnet's
    rail elevation in time before gridding. The gap sensor's white noise enters the profile as
    broadband 'irregularity' that the twin's controller (kv d(gap)/dt) turns into magnet acceleration
    the real magnet never had (the real controller saw the true gap), which biases kp and kv low; the
    profile is only trusted below the frequency where the irregularity content exceeds that noise. A polynomial trend of order ``detrend_order`` in time is
    removed per magnet (integration drift and offsets; a periodic FFT high-pass was tried and rejected:
    on a record of a few seconds its wrap-around leaves broadband errors). Each magnet's profile is interpolated on a common
    grid (``spacing_m``, default distance per sample) and the magnets covering a grid point are averaged.
    ``accel_mps2``, ``gap_m``: (n, m) on the common ``time_s``; ``position_m`` (n,) increasing."""
    t = np.asarray(time_s, dtype=float)
    a, g = np.atleast_2d(np.asarray(accel_mps2, float)), np.atleast_2d(np.asarray(gap_m, float))
    if a.shape != g.shape or a.shape[0] != t.size or len(magnet_offsets_m) != a.shape[1]:
        raise UserError("irregularity: accel, gap and magnet offsets must cover the same magnets and samples")
    pos = np.asarray(position_m, float)
    if np.any(np.diff(pos) <= 0):
        raise UserError("/testline/vehicle/position: the irregularity reconstruction needs a moving vehicle (increasing position_m)")
    fs = 1.0 / float(np.median(np.diff(t)))
    x = pos[:, None] + np.asarray(magnet_offsets_m, float)[None, :]
    raw = g - nominal_gap_m
    if deflection_m is not None:
        raw = raw - np.asarray(deflection_m, float).reshape(raw.shape)
    elif modal is not None and magnet_force_n is not None:
        n, m = x.shape
        phi = modal.shapes_at(x.ravel()).reshape(n, m, -1)
        q = -np.einsum("nmj,m->nj", phi, np.asarray(magnet_force_n, float)) / modal.omega_rad_s ** 2
        raw = raw - np.einsum("nmj,nj->nm", phi, q)
    from scipy.integrate import cumulative_trapezoid
    v = cumulative_trapezoid(a - a.mean(axis=0), t, axis=0, initial=0.0)
    z = cumulative_trapezoid(v, t, axis=0, initial=0.0)
    y = raw + z
    # remove a low-order polynomial trend per magnet (integration drift, static offsets): the error
    # it leaves is smooth (long wavelength) and produces no magnet acceleration in the twin
    tt = (t - t.mean()) / max(np.ptp(t), 1e-9)
    V = np.vander(tt, detrend_order + 1)
    y = y - V @ np.linalg.lstsq(V, y, rcond=None)[0]
    if lowpass_hz is not None and lowpass_hz < 0.45 * fs:
        from scipy.signal import butter, sosfiltfilt
        y = sosfiltfilt(butter(4, float(lowpass_hz), fs=fs, output="sos"), y, axis=0)
    ds = spacing_m or max(float(np.median(np.diff(pos))), 1e-3)
    xg = np.arange(float(x.min()), float(x.max()) + ds, ds)
    prof = np.full((x.shape[1], xg.size), np.nan)
    for k in range(x.shape[1]):
        inside = (xg >= x[0, k]) & (xg <= x[-1, k])
        prof[k, inside] = np.interp(xg[inside], x[:, k], y[:, k])
    # align the magnets' smooth trends (each was detrended on its own time window) to their mean,
    # so that averaging leaves no steps where the set of covering magnets changes
    for _ in range(4):
        mean = np.nanmean(prof, axis=0)
        for k in range(prof.shape[0]):
            ok_k = np.isfinite(prof[k])
            if ok_k.sum() > detrend_order + 2:
                xx = (xg[ok_k] - xg[ok_k].mean()) / max(np.ptp(xg[ok_k]), 1e-9)
                V = np.vander(xx, detrend_order + 1)
                d = prof[k, ok_k] - mean[ok_k]
                prof[k, ok_k] -= V @ np.linalg.lstsq(V, d, rcond=None)[0]
    acc = np.nansum(prof, axis=0)
    cnt = np.sum(np.isfinite(prof), axis=0)
    ok = cnt > 0
    return xg, np.interp(xg, xg[ok], acc[ok] / cnt[ok])
