"""Magnetic-force layer (000 Sec. 4.2.2, Eqs. 26-27): controller gains kp, kv, ka from the measured
electromagnet accelerations of vehicle passes, on the coupled twin with the UPDATED guideway.

Model: the twin driven along the recording's position channel (``irregularity.twin_input.
simulate_recorded_pass``: starts at rest one sample before the window, measured speed) by the
pass's unloaded irregularity (``PassEvidence``; the pipeline builds it ONCE per pass with
``profile_for_twin`` on the guideway-updated twin and the nominal gains -- not per candidate gain
set: the profile depends on the gains only through the girder deflection under the dynamic magnet
forces, a second-order effect). Compared: the magnet accelerations band-passed (zero-phase
Butterworth, order 4) to the band the profile carries, on the samples where that magnet is over
the valid profile (past the taper + ``margin_m``) and after ``skip_s`` of start transient.
Objectives (MOPSO; 000's Eq. 27 text was lost, these follow its description "simulated vs measured
acceleration, their averages, number of moments"): f1 = NRMSE = rms(a_sim - a_meas) / rms(a_meas),
f2 = 1 - Pearson correlation of a_sim and a_meas (pooled over magnets and passes).

One coupled simulation costs ~0.1 s per simulated second (2 ms internal step: the compared band
ends below ~90 Hz; 1 ms changes the true-gain NRMSE by < 0.001), so the global search runs on an
Elman surrogate of (f1, f2) trained on optimal-LHS samples (``use_surrogate``, default), MOPSO + GRP
pick a point, and a Levenberg-Marquardt fit of the acceleration time series on the DIRECT model
(forward-difference Jacobian, reused for the uncertainty) polishes it.

Identifiability: with F = C (I/gap)^2 and C fixed by the static load at (I0, g0), the full
nonlinear model is invariant under a common scale of (kp, kv, ka, I0) (C scales as 1/I0^2): the
gains are confounded with the static current and the magnet constant. The Jacobian w.r.t.
(kp, kv, ka, I0) exposes this ridge; kp/I0, kv/I0, ka/I0 are reported. With ``fix_static_current``
(default) I0 is taken as known from the design (data sheet) and the gains are GIVEN I0. Even then
one direction is weak: for a single magnet following the rail, m z'' + kgap dg = kI (kp dg + kv dg'
- ka z''), the regressors dg, dg', z'' are nearly collinear around the closed-loop resonance
(whitened-Jacobian condition ~70 on the test passes, weak direction ~ kp^0.3 kv^0.56 ka^0.76).
A short pass (< ~3 s of comparable samples per magnet) leaves that direction to the model error
(+20..40 % bias seen); ~8 s per magnet brings it to a few percent.

Uncertainty (model error included): the residual is NOT white measurement noise (the profile
carries the gap-sensor and integrated accelerometer noise into the model input, the profile is
band-limited, ...). So the covariance is the sandwich A^-1 B A^-1 with A = J^T J and B the
long-run covariance of the score series S_t = sum_magnets J_t r_t (Newey-West, Bartlett weights
up to ``block_s`` seconds of lag, about the period of the band's low corner; a cluster version
over 1 s blocks was tried first: with 3-10 blocks per pass it scattered by a factor ~2): the
scatter of the residual's projection on the sensitivities, i.e. the RANDOM part of the model error.
It misses a SYSTEMATIC model error, which the fit absorbs along the weak direction: on the sample
bag paper_pass the true gains came out +7 / +10 / +18 % (kp, kv, ka) with sandwich stds of 0.4 /
0.8 / 1.2 %; driving the same fit with the TRUE irregularity instead of the reconstructed one gives
+1.6 / +2.5 / +3.7 %, and the reconstruction's grid alone (2 cm -> 1 cm bins) moved the estimate
to -2.4 / -3.8 / -5.8 %: a ~1 % amplitude error of the profile at the 0.3-0.5 m waves moves the
weak direction by ~10-20 %. Per-magnet and split-half refits agree to 1-4 % there (the error is
common to all magnets and all the time), so their spread cannot reveal it; sub-band refits can
(each band's sensitivities differ, a model error pulls each band elsewhere):
``band_split_model_error`` adds the between-band random-effects variance along each eigen-direction
of the sandwich (``model_error``, default on; 3 bands of equal measured energy). A model error
that acts like a gain change in every band is invisible to that split; two such nuisances are
added with stated priors, linearised (shift of the estimate g = pinv(J) dp/d(nuisance), covariance
sigma^2 g g^T, no extra simulations): the profile amplitude (1 %: the reconstruction's transfer
at the 0.3-1 m waves measured 0.985-0.999 on paper_pass) and the timing of model vs record
(0.1 ms, twice the 0.05 ms lag the 8-25 Hz band of paper_pass showed at the true gains, next
to a 1 % gain). On the pipeline test pass the best-determined combination was 1.2 % off with a
sandwich std of 0.07 %; a timing error of ~0.2 ms moves it by that much. The reported
covariance is sandwich + band-split + nuisance. A gain is flagged identifiable when its relative std
<= ``max_rel_std`` (default 2.5 %: +-5 % at 2 sigma); the principal directions of the total
covariance are reported as log-linear combinations (identifiable when their std <= 1 %,
``identifiability.COMBINATION_MAX_REL_STD``: +-2 % at 2 sigma).
Why by hand: LM polish is scipy's; the sandwich, the random-effects estimate and the combinations
are a few lines of algebra specific to this residual.
"""
from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Sequence

import numpy as np
from scipy import signal
from scipy.optimize import least_squares

from maglev_ros.errors import UserError
from maglev_ros.parallel import SERIAL, Executor
from maglev_ros.progress import NULL, Progress
from maglev_ros.twin.design import TwinConfig, with_levitation
from maglev_ros.updating.grp import grey_relational_projection
from maglev_ros.updating.identifiability import COMBINATION_MAX_REL_STD, Combination, Identifiability, analyse
from maglev_ros.updating.mopso import MOPSO, ParetoResult
from maglev_ros.updating.parameters import MAGNET_PARAMS, SYMBOLS, magnet_space
from maglev_ros.updating.sampling import optimal_lhs


def nrmse(pred: np.ndarray, meas: np.ndarray) -> float:
    d = float(np.sqrt(np.mean(np.asarray(meas) ** 2)))
    return float(np.sqrt(np.mean((np.asarray(pred) - np.asarray(meas)) ** 2)) / d) if d > 0 else float("inf")


def corr(pred: np.ndarray, meas: np.ndarray) -> float:
    a, b = np.ravel(pred) - np.mean(pred), np.ravel(meas) - np.mean(meas)
    den = float(np.sqrt((a @ a) * (b @ b)))
    return float(a @ b / den) if den > 0 else 0.0


def _bandpass(x: np.ndarray, fs_hz: float, band_hz) -> np.ndarray:
    lo, hi = float(band_hz[0]), min(float(band_hz[1]), 0.45 * fs_hz)
    sos = signal.butter(4, [lo, hi], btype="band", fs=fs_hz, output="sos")
    x = np.asarray(x, float)
    return signal.sosfiltfilt(sos, x - x.mean(axis=0), axis=0)


def above_noise_hz(accel_mps2: np.ndarray, fs_hz: float, band_hz, snr: float = 10.0) -> float:
    """Upper band edge where the measured accelerations stand above their noise floor: the end of
    the contiguous run of frequencies, around the spectrum's peak inside ``band_hz``, where the
    magnets' mean Welch PSD exceeds ``snr`` x the floor (median PSD over the top half of the
    Nyquist band: white sensor noise). ``band_hz[1]`` when the PSD never sinks that low.

    Why: above the rail's shortest waves the measurement is sensor noise, while the twin, driven by
    a reconstructed rail whose error there is coherent over the magnets (coherence 0.6, ~3 um at
    0.08-0.2 m on a 9 m/s test pass; cause not traced), predicts 10x the measured level; comparing
    there fits noise and made every gain unidentifiable (std 40-250 %)."""
    lo, hi = float(band_hz[0]), float(band_hz[1])
    x = np.asarray(accel_mps2, float)
    x = x.reshape(x.shape[0], -1)
    if x.shape[0] < 64:
        return hi
    f, P = signal.welch(x - x.mean(axis=0), fs=fs_hz, nperseg=min(1024, x.shape[0]), axis=0)
    P = P.mean(axis=1)
    top = f >= 0.25 * fs_hz
    if top.sum() < 4:
        return hi
    floor = float(np.median(P[top]))
    inb = np.flatnonzero((f >= lo) & (f <= hi))
    if inb.size == 0 or floor <= 0:
        return hi
    k = inb[np.argmax(P[inb])]
    while k + 1 < f.size and f[k + 1] <= hi and P[k + 1] > snr * floor:
        k += 1
    if k + 1 >= f.size or f[k + 1] > hi:
        return hi
    return float(max(f[k + 1], 2.0 * lo))


@dataclass(frozen=True, eq=False)
class PassEvidence:
    """One pass for the magnet layer (build it with ``make_evidence``).

    ``time_s`` (n,): evenly spaced model sample times (the recording's clock); ``accel_mps2`` (n, m):
    measured accelerations of ``magnets`` (1-based), band-passed to ``band_hz`` at the recording rate
    and sampled at ``time_s``; ``compare`` (n, m): samples used; the position channel
    (``position_time_s``, ``position_m``, ``speed_mps``); the unloaded irregularity (x, r) and how
    it was obtained (``irregularity_method``)."""
    time_s: np.ndarray
    accel_mps2: np.ndarray
    magnets: tuple[int, ...]
    position_time_s: np.ndarray
    position_m: np.ndarray
    speed_mps: np.ndarray
    irregularity_x_m: np.ndarray
    irregularity_m: np.ndarray
    compare: np.ndarray
    band_hz: tuple[float, float]
    sensor_delay_s: float = 0.0
    label: str = ""
    irregularity_method: str = ""
    record_time_s: np.ndarray | None = None      # full-rate times (band-pass grid); time_s = record_time_s[::step]
    step: int = 1

    @property
    def fs_hz(self) -> float:
        return 1.0 / float(np.median(np.diff(self.time_s)))

    @property
    def duration_s(self) -> float:
        return float(self.time_s[-1] - self.time_s[0])

    @property
    def compared_s(self) -> list[float]:
        return [float(c) / self.fs_hz for c in self.compare.sum(axis=0)]

    def position_channel(self):
        return SimpleNamespace(time_s=self.position_time_s, data=np.column_stack([self.position_m, self.speed_mps]),
                               channels=("position_m", "speed_mps"))


def make_evidence(time_s, accel_mps2, magnets: Sequence[int], position_time_s, position_m, speed_mps,
                  irregularity, magnet_offsets_m: Sequence[float], *, valid_range_m=None, band_hz=(1.0, 80.0),
                  model_fs_hz: float = 500.0, skip_s: float = 0.3, margin_m: float = 0.0,
                  sensor_delay_s: float = 0.0, max_window_s: float | None = None, label: str = "",
                  irregularity_method: str = "", noise_snr: float | None = 10.0) -> PassEvidence:
    """Evidence of one pass from full-rate recorded accelerations (n, m) at ``time_s``.

    ``valid_range_m``: list of (lo, hi) stretches where the irregularity is valid (default: the
    whole (x, r) grid); a magnet's sample is compared when its position (reference position at
    t - ``sensor_delay_s`` + offset) is inside a stretch by at least ``margin_m``, after ``skip_s``
    (start transient) and within ``max_window_s`` of the start. ``noise_snr``: the band ends where
    the measured accelerations sink into their noise floor (:func:`above_noise_hz`; None: keep
    ``band_hz``)."""
    t = np.asarray(time_s, float)
    a = np.atleast_2d(np.asarray(accel_mps2, float))
    mags = tuple(int(m) for m in magnets)
    if a.shape != (t.size, len(mags)):
        raise UserError("magnet evidence: accel must be (n samples, n magnets) on time_s")
    if t.size < 16:
        raise UserError(f"pass {label}: fewer than 16 magnet acceleration samples")
    fs = 1.0 / float(np.median(np.diff(t)))
    k = max(1, int(math.floor(fs / float(model_fs_hz) + 1e-9)))
    fs_m = fs / k
    band = (float(band_hz[0]), float(min(band_hz[1], 0.4 * fs_m)))
    if not 0 < band[0] < band[1]:
        raise UserError(f"pass {label}: empty comparison band {band} Hz")
    if max_window_s is not None:
        keep = t <= t[0] + float(max_window_s)
        t, a = t[keep], a[keep]
    if noise_snr is not None:
        band = (band[0], above_noise_hz(a, fs, band, float(noise_snr)))
    af = _bandpass(a, fs, band)
    sel = np.arange(0, t.size, k)
    ts = t[sel]
    pt, px, pv = (np.asarray(v, float) for v in (position_time_s, position_m, speed_mps))
    x_ref = np.interp(ts - float(sensor_delay_s), pt, px)
    offs = np.asarray(magnet_offsets_m, float)
    X = x_ref[:, None] + offs[[m - 1 for m in mags]][None, :]
    xg = np.asarray(irregularity[0], float)
    ranges = [(float(xg[0]), float(xg[-1]))] if valid_range_m is None else list(valid_range_m)
    inside = np.zeros(X.shape, bool)
    for lo, hi in ranges:
        inside |= (X >= lo + margin_m) & (X <= hi - margin_m)
    compare = inside & (ts >= ts[0] + float(skip_s))[:, None]
    if compare.sum() < 16:
        raise UserError(f"pass {label}: fewer than 16 magnet samples over the valid irregularity after "
                        f"{skip_s} s of start transient (pass too short for the magnet layer)")
    return PassEvidence(ts, af[sel], mags, pt, px, pv, xg, np.asarray(irregularity[1], float), compare, band,
                        float(sensor_delay_s), label, irregularity_method, t, k)


class MagnetModel:
    """Coupled twin predictions of the compared (band-passed) magnet accelerations for given gains."""

    def __init__(self, config: TwinConfig, line, evidence: PassEvidence, dt_max_s: float | None = 2e-3):
        self.config, self.line, self.ev = config, line, evidence
        self.dt_max_s = dt_max_s
        self.measured = evidence.accel_mps2[evidence.compare]
        self.rows = np.nonzero(evidence.compare)[0]        # time index of each compared sample
        self.n_evaluations = 0

    def predict_full(self, values: Sequence[float], static_current_a: float | None = None) -> np.ndarray:
        """Band-passed predictions (n, m) on the evidence's time grid."""
        from maglev_ros.irregularity.twin_input import simulate_recorded_pass
        kw = dict(zip(MAGNET_PARAMS, map(float, values)))
        if static_current_a is not None:
            kw["static_current_a"] = float(static_current_a)
        cfg = with_levitation(self.config, **kw)
        ev = self.ev
        res, _, _ = simulate_recorded_pass(cfg, self.line, ev.position_channel(),
                                           (ev.irregularity_x_m, ev.irregularity_m), ev.time_s,
                                           sensor_delay_s=ev.sensor_delay_s, dt_max_s=self.dt_max_s)
        self.n_evaluations += 1
        # same band-pass as the measured: on the recording's grid (linear interpolation of the model
        # samples), then every step-th sample (filtering at the model rate instead left errors of
        # up to 0.8 of the signal near the record end on a test pass)
        tr = ev.time_s if ev.record_time_s is None else ev.record_time_s
        P = np.column_stack([np.interp(tr, res.time_s, res.magnet_accel_mps2[:, m - 1]) for m in ev.magnets])
        fs_r = 1.0 / float(np.median(np.diff(tr)))
        return _bandpass(P, fs_r, ev.band_hz)[::ev.step][:ev.time_s.size]

    def predict(self, values: Sequence[float], static_current_a: float | None = None) -> np.ndarray:
        return self.predict_full(values, static_current_a)[self.ev.compare]


def sandwich_cov(J: np.ndarray, r: np.ndarray, series: np.ndarray, time_index: np.ndarray,
                 max_lag: int) -> tuple[np.ndarray, int]:
    """Heteroscedasticity-and-autocorrelation-consistent sandwich A^-1 B A^-1 (Newey-West, Bartlett
    weights up to ``max_lag`` samples) of a least-squares estimate. The score of time sample t of a
    series is S_t = sum over its magnets of J_i r_i; B = sum_l w_l (Gamma_l + Gamma_l^T) over the
    series (passes; independent of each other). Returns (cov, max_lag)."""
    A = J.T @ J
    p = J.shape[1]
    B = np.zeros((p, p))
    for sid in np.unique(series):
        sel = series == sid
        ti = time_index[sel]
        n = int(ti.max()) + 1
        S = np.zeros((n, p))
        np.add.at(S, ti, J[sel] * r[sel, None])
        S -= S.mean(axis=0)
        L = int(min(max_lag, n - 1))
        nfft = 1 << int(np.ceil(np.log2(2 * n)))
        F = np.fft.rfft(S, nfft, axis=0)
        G = np.fft.irfft(F[:, :, None] * np.conj(F[:, None, :]), nfft, axis=0)   # G[l] = sum_t S_{t+l} S_t^T
        w = 1.0 - np.arange(L + 1) / (L + 1.0)
        B += G[0] + np.einsum("l,lij->ij", w[1:], G[1:L + 1] + np.transpose(G[1:L + 1], (0, 2, 1)))
    Ai = np.linalg.pinv(A)
    return Ai @ B @ Ai, max_lag


def _energy_band_edges(meas: np.ndarray, compare: np.ndarray, fs_hz: float, band_hz, n_bands: int) -> list[float]:
    """Edges splitting ``band_hz`` into ``n_bands`` bands of equal measured-acceleration energy."""
    from scipy.signal import welch
    lo, hi = float(band_hz[0]), min(float(band_hz[1]), 0.45 * fs_hz)
    x = np.where(compare, meas, 0.0)
    f, P = welch(x, fs=fs_hz, nperseg=min(1024, x.shape[0]), axis=0)
    P = P.sum(axis=1) * ((f >= lo) & (f <= hi))
    c = np.cumsum(P)
    if c[-1] <= 0:
        return list(np.geomspace(lo, hi, n_bands + 1))
    c = c / c[-1]
    inner = [float(np.interp(q, c, f)) for q in np.arange(1, n_bands) / n_bands]
    return [lo] + inner + [hi]


def _phase_randomised(x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Surrogate of the (n, m) series x with the same auto- and cross-spectra (one random phase per
    frequency shared by the columns) and no relation to anything else."""
    F = np.fft.rfft(x, axis=0)
    ph = np.exp(2j * np.pi * rng.random(F.shape[0]))
    ph[0] = 1.0
    return np.fft.irfft(F * ph[:, None], n=x.shape[0], axis=0)


def band_split_model_error(J_full: Sequence[np.ndarray], R_full: Sequence[np.ndarray],
                           meas_full: Sequence[np.ndarray], compare: Sequence[np.ndarray],
                           fs_hz: Sequence[float], band_hz: Sequence[tuple[float, float]], cov: np.ndarray,
                           n_bands: int = 3, n_surrogates: int = 40, seed: int = 0) -> tuple[np.ndarray, dict]:
    """Model-error covariance of the gain estimate from the disagreement of sub-band refits.

    With a correct model every frequency band of the compared accelerations points to the same
    gains (up to noise); a model error (e.g. an irregularity profile 1 % off at the short waves)
    pulls each band elsewhere along the weak direction. Each pass's band is split into
    ``n_bands`` bands of equal measured energy; in band b the linearised refit from the optimum is
    e_b = -pinv(J_b) r_b (J_b, r_b: Jacobian columns and residual band-passed, passes pooled). Its
    noise covariance S_b comes from ``n_surrogates`` phase-randomised copies of the residual (same
    spectra, no relation to the sensitivities; a per-band Newey-West sandwich was tried first: on
    pure white noise its Cochran Q came out 2-3x the degrees of freedom, i.e. spurious
    heterogeneity). Along each eigen-direction v_k of the pooled sandwich ``cov`` the between-band
    variance tau_k^2 is the DerSimonian-Laird random-effects estimate from y_b = v_k.e_b,
    s_b^2 = v_k^T S_b v_k. The error is systematic (the same in the full-band estimate), so it
    enters the full estimate's covariance undivided: V diag(tau^2) V^T. ``J_full[i]``: (p, n, m)
    full-series Jacobian of pass i, ``R_full[i]``: (n, m) residual at the optimum. Returns
    (covariance, info)."""
    p = cov.shape[0]
    edges = [_energy_band_edges(M, C, fs, bd, n_bands) for M, C, fs, bd in zip(meas_full, compare, fs_hz, band_hz)]
    R0 = [np.where(C, R, 0.0) for R, C in zip(R_full, compare)]
    G, used = [], []
    for b in range(n_bands):
        Jb, ok = [], []
        for i, (Jf, C, fs) in enumerate(zip(J_full, compare, fs_hz)):
            lo, hi = edges[i][b], edges[i][b + 1]
            if 0 < lo < hi:
                Jb.append(np.column_stack([_bandpass(Jf[j], fs, (lo, hi))[C] for j in range(p)]))
                ok.append(i)
        if Jb:
            G.append(np.linalg.pinv(np.vstack(Jb)))
            used.append((b, ok))

    def band_estimates(R):
        out = []
        for (b, ok), Gb in zip(used, G):
            rb = np.concatenate([_bandpass(R[i], fs_hz[i], (edges[i][b], edges[i][b + 1]))[compare[i]] for i in ok])
            out.append(-Gb @ rb)
        return np.array(out)

    E = band_estimates(R0)
    rng = np.random.default_rng(seed)
    sur = np.array([band_estimates([_phase_randomised(R, rng) for R in R0]) for _ in range(int(n_surrogates))])
    covs = [np.cov(sur[:, b, :], rowvar=False).reshape(p, p) for b in range(len(used))]
    w, V = np.linalg.eigh(cov)
    tau2 = np.zeros(p)
    q_stats = []
    if len(used) >= 2 and n_surrogates >= 2:
        for k in range(p):
            v = V[:, k]
            y = E @ v
            wt = 1.0 / np.array([max(float(v @ S @ v), 1e-300) for S in covs])
            ybar = float((wt * y).sum() / wt.sum())
            Q = float((wt * (y - ybar) ** 2).sum())
            den = float(wt.sum() - (wt ** 2).sum() / wt.sum())
            tau2[k] = max(0.0, (Q - (len(y) - 1)) / den) if den > 0 else 0.0
            q_stats.append(Q)
    Me = (V * tau2) @ V.T
    info = {"method": "between-band heterogeneity of linearised sub-band refits (DerSimonian-Laird "
                      "random effects along the sandwich's eigen-directions; band noise from "
                      "phase-randomised residuals)",
            "n_bands": n_bands, "n_surrogates": int(n_surrogates),
            "band_edges_hz": [[float(x) for x in e] for e in edges],
            "band_estimates_log": E.tolist(),
            "band_rel_std": [np.sqrt(np.maximum(np.diag(S), 0)).tolist() for S in covs],
            "directions": V.T.tolist(), "sandwich_std_log": np.sqrt(np.maximum(w, 0)).tolist(),
            "model_error_std_log": np.sqrt(tau2).tolist(), "cochran_q": q_stats}
    return Me, info


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
    theta_cov: np.ndarray | None = None         # sandwich covariance of log(gains)
    uncertainty: dict = field(default_factory=dict)

    def value(self, name: str) -> float:
        return self.values[self.names.index(name)]

    def to_dict(self) -> dict:
        return {"names": list(self.names), "nominal": list(self.nominal), "values": list(self.values),
                "std": list(self.std), "identifiable": list(self.identifiable),
                "static_current_a": self.static_current_a, "identifiability": self.identifiability.to_dict(),
                "magnet_accel_nrmse": {"nominal": self.nrmse_nominal, "updated": self.nrmse_updated},
                "pareto": self.pareto.to_dict(), "grp_index": self.grp_index,
                "n_model_evaluations": self.n_model_evaluations, "wall_time_s": self.wall_time_s,
                "surrogate_score": self.surrogate_score, "uncertainty": self.uncertainty}


MAGNET_COMBINATIONS = (("kp/I0", (1.0, 0.0, 0.0, -1.0)), ("kv/I0", (0.0, 1.0, 0.0, -1.0)),
                       ("ka/I0", (0.0, 0.0, 1.0, -1.0)))


def _expression(c: np.ndarray, names: Sequence[str]) -> str:
    parts = [f"{SYMBOLS.get(n, n)}^{v:.2f}" for n, v in zip(names, c) if round(abs(v), 2) > 0]
    return " ".join(parts)


@dataclass(frozen=True, eq=False)
class _SampleSims:
    """One surrogate sample's coupled simulations, every pass (an executor's work item): on copies
    of the models, whose evaluation counts the caller keeps."""
    models: list
    space: object

    def __call__(self, theta) -> list[np.ndarray]:
        values = self.space.from_theta(theta)
        return [copy.copy(m).predict_full(values) for m in self.models]


class MagnetLayer:
    """fit(config_with_updated_guideway, line, passes) -> MagnetUpdate.

    ``n_samples``: optimal-LHS direct simulations for the surrogate; ``polish_max_nfev``: LM
    iterations' residual evaluations on the direct model (each iteration adds 3 for the Jacobian);
    ``block_s``: maximal lag [s] of the sandwich covariance; ``max_rel_std``: identifiable when the
    relative std is at most this; ``dt_max_s``: the twin's internal step for the layer; ``model_error``:
    add the between-band model-error covariance (``band_split_model_error``, ``n_bands`` bands) and
    the nuisance covariance (``profile_amplitude_rel_std``: relative std of the irregularity
    profile's amplitude, ``timing_std_s``: std of the model-vs-record timing) to the sandwich."""

    def __init__(self, rel_range: float = 0.45, use_surrogate: bool = True, n_samples: int = 60,
                 n_particles: int = 50, archive_size: int = 40, n_iterations: int = 100, n_grid: int = 7,
                 polish_max_nfev: int = 8, fix_static_current: bool = True, seed: int = 0,
                 surrogate_kwargs: dict | None = None, block_s: float = 1.0, max_rel_std: float = 0.025,
                 dt_max_s: float | None = 2e-3, jac_step: float = 0.01, model_error: bool = True,
                 n_bands: int = 3, n_surrogates: int = 40, profile_amplitude_rel_std: float = 0.01,
                 timing_std_s: float = 1e-4):
        self.rel_range, self.use_surrogate, self.n_samples = rel_range, bool(use_surrogate), int(n_samples)
        self.mopso = dict(n_particles=n_particles, archive_size=archive_size, n_iterations=n_iterations,
                          n_grid=n_grid, inertia=0.5, c1=1.0, c2=2.0, mutation_rate=0.1, seed=seed)
        self.polish_max_nfev = int(polish_max_nfev)
        self.fix_static_current, self.seed = bool(fix_static_current), seed
        self.surrogate_kwargs = surrogate_kwargs or {}
        self.block_s, self.max_rel_std = float(block_s), float(max_rel_std)
        self.dt_max_s, self.jac_step = dt_max_s, float(jac_step)
        self.model_error, self.n_bands, self.n_surrogates = bool(model_error), int(n_bands), int(n_surrogates)
        self.profile_amplitude_rel_std, self.timing_std_s = float(profile_amplitude_rel_std), float(timing_std_s)

    def fit(self, config: TwinConfig, line, passes: Sequence[PassEvidence], progress: Progress = NULL,
            executor: Executor = SERIAL) -> MagnetUpdate:
        """``executor``: where the surrogate's training simulations run (:mod:`maglev_ros.parallel`;
        the result is the same wherever they run)."""
        t_start = time.perf_counter()
        if not passes:
            raise UserError("magnet layer: expected at least one pass with magnet accelerations")
        space = magnet_space(config, self.rel_range)
        models = [MagnetModel(config, line, p, self.dt_max_s) for p in passes]
        meas = np.concatenate([m.measured for m in models])
        series = np.concatenate([np.full(m.rows.size, i) for i, m in enumerate(models)])
        tindex = np.concatenate([m.rows for m in models])
        lag = int(math.ceil(max(self.block_s * m.ev.fs_hz for m in models)))

        def predict_all(values, i0=None):
            return np.concatenate([m.predict(values, i0) for m in models])

        full_cache: dict[bytes, list[np.ndarray]] = {}

        def key_of(theta) -> bytes:
            return np.round(np.asarray(theta, float), 12).tobytes()

        def full_theta(theta):
            key = key_of(theta)
            if key not in full_cache:
                full_cache[key] = [m.predict_full(space.from_theta(theta)) for m in progress.steps(models)]
            return full_cache[key]

        def objectives(values):
            p = predict_all(values)
            return np.array([nrmse(p, meas), 1.0 - corr(p, meas)])

        lo, hi = space.theta_bounds
        surrogate_score = None
        cache: dict[bytes, np.ndarray] = {}

        def pred_theta(theta):
            key = key_of(theta)
            if key not in cache:
                cache[key] = np.concatenate([F[m.ev.compare] for F, m in zip(full_theta(theta), models)])
            return cache[key]

        progress.stage("magnet layer: coupled simulations for the surrogate",
                       total=len(models) * (1 + (self.n_samples if self.use_surrogate else 0)))
        nominal_pred = pred_theta(np.zeros(space.dim))
        if self.use_surrogate:
            from maglev_ros.updating.surrogate import train_and_score
            U = optimal_lhs(self.n_samples, space.dim, seed=self.seed)
            Xs = np.array([space.from_unit(u) for u in U])
            # the samples' coupled simulations are independent: run them on the executor, then read
            # them from the cache as before (the serial loop is the same computation)
            thetas = [space.to_theta(x) for x in Xs]
            todo = list({key_of(t): t for t in thetas if key_of(t) not in full_cache}.items())
            sims = executor.map(_SampleSims(models, space), [t for _, t in todo],
                                done=lambda i: progress.advance(len(models)))
            for (key, _), full in zip(todo, sims):
                full_cache[key] = full
            for m in models:
                m.n_evaluations += len(todo)
            Y = np.array([[nrmse(p, meas), 1.0 - corr(p, meas)] for p in (pred_theta(space.to_theta(x)) for x in Xs)])
            Y = np.maximum(Y, 1e-9)
            progress.stage("magnet layer: surrogate training")
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
        progress.stage("magnet layer: swarm (MOPSO)")
        pareto = MOPSO(**self.mopso).minimize(batch, lo, hi, x0=np.vstack([np.zeros(space.dim), best_sample]))
        grp = grey_relational_projection(pareto.f)
        theta0 = np.clip(pareto.x[grp.index], lo, hi)

        # ---- direct polish: Levenberg-Marquardt-like trust region on the acceleration series ----
        progress.stage("magnet layer: polish on the coupled model (simulations)")
        h = self.jac_step

        def residual(theta):
            return pred_theta(theta) - meas

        def steps(theta):
            out = []
            for j in range(space.dim):
                e = np.zeros(space.dim)
                e[j] = h if theta[j] + h <= hi[j] else -h
                out.append(e)
            return out

        def jac(theta):
            f0 = pred_theta(theta)
            return np.column_stack([(pred_theta(theta + e) - f0) / e[j] for j, e in enumerate(steps(theta))])
        sol = least_squares(residual, theta0, jac=jac, bounds=(lo, hi), x_scale=0.1, xtol=1e-4, ftol=1e-6,
                            max_nfev=max(1, self.polish_max_nfev))
        theta = sol.x
        values = space.clip(space.from_theta(theta))
        r_opt = residual(theta)
        J = jac(theta)
        # ---- uncertainty: sandwich (Newey-West over time) + model error (between-band spread) ----
        progress.stage("magnet layer: uncertainty (simulations)")
        cov_sw, nb = sandwich_cov(J, r_opt, series, tindex, lag)
        F0 = full_theta(theta)
        J_full = [np.stack([(full_theta(theta + e)[i] - F0[i]) / e[j] for j, e in enumerate(steps(theta))])
                  for i in range(len(models))]
        R_full = [F0[i] - m.ev.accel_mps2 for i, m in enumerate(models)]
        cov_me, me_info = band_split_model_error(
            J_full, R_full, [m.ev.accel_mps2 for m in models], [m.ev.compare for m in models],
            [m.ev.fs_hz for m in models], [m.ev.band_hz for m in models], cov_sw, self.n_bands,
            self.n_surrogates, self.seed)
        # nuisance model errors the data cannot separate from the gains (they act like a gain change in
        # EVERY band, so the band split misses them): profile amplitude scale and timing. Linearised
        # shift of the estimate per unit nuisance: g = pinv(J) dp/dnuisance; covariance sigma^2 g g^T.
        Ji = np.linalg.pinv(J)
        p_opt = r_opt + meas
        dp_dt = np.concatenate([np.gradient(F, axis=0)[m.ev.compare] * m.ev.fs_hz for F, m in zip(F0, models)])
        g_amp, g_tau = Ji @ p_opt, Ji @ dp_dt
        cov_nu = (self.profile_amplitude_rel_std ** 2) * np.outer(g_amp, g_amp) \
            + (self.timing_std_s ** 2) * np.outer(g_tau, g_tau)
        cov = cov_sw + cov_me + cov_nu if self.model_error else cov_sw
        rel = np.sqrt(np.maximum(np.diag(cov), 0.0))
        # ---- identifiability incl. the static current (exact ridge of the common scale) ----------
        i0 = config.levitation.static_current_a
        p_i0 = predict_all(values, i0 * math.exp(h))
        J4 = np.column_stack([J, (p_i0 - (r_opt + meas)) / h])
        sigma = float(np.sqrt(np.mean(r_opt ** 2))) or 1.0
        names4 = space.names + ("static_current_a",)
        vals4 = np.concatenate([values, [i0]])
        ident4 = analyse(J4 / sigma, names4, vals4, (), rel_tol=1e-2, max_rel_std=np.inf, estimable_tol=2e-2)
        combos = []
        for expr, c4 in MAGNET_COMBINATIONS:      # given the data: std of kp/I0 = rel std of kp given I0
            c = np.asarray(c4[:3])
            r = float(np.sqrt(max(c @ cov @ c, 0.0)))
            val = float(np.prod(vals4 ** np.asarray(c4)))
            combos.append(Combination(expr, tuple(map(float, c4)), val, r * val, r <= COMBINATION_MAX_REL_STD))
        w, V = np.linalg.eigh(cov)
        for k in range(space.dim):                 # principal log-combinations, best determined first
            c = V[:, k] / V[np.argmax(np.abs(V[:, k])), k]
            # the exponents as printed (2 decimals) ARE the combination: value and std follow them (with
            # kp ~ 1e4 and ka ~ 0.3, an exponent off by 0.005 moves the value by ~1 %)
            c = np.round(c / np.max(np.abs(c)), 2)
            r = float(np.sqrt(max(c @ cov @ c, 0.0)))
            val = float(np.prod(values ** c))
            combos.append(Combination(_expression(c, space.names), tuple(map(float, c)) + (0.0,), val, r * val,
                                      r <= COMBINATION_MAX_REL_STD))
        ident = Identifiability(ident4.names, ident4.singular_values, ident4.ridge_directions, ident4.theta_cov,
                                ident4.param_std, ident4.identifiable, tuple(combos))
        if self.fix_static_current:
            std = tuple(float(s * v) for s, v in zip(rel, values))
            identifiable = tuple(bool(s <= self.max_rel_std) for s in rel)
        else:
            std = tuple(None for _ in space.names)
            identifiable = tuple(False for _ in space.names)
        sv = np.linalg.svd(J / sigma, compute_uv=False)
        unc = {"method": "sandwich, Newey-West (Bartlett) over time" + (" + model error from the between-band "
                                                                         "spread of sub-band refits" if self.model_error else ""),
               "max_lag_s": self.block_s, "max_lag": nb,
               "rel_std": rel.tolist(), "sandwich_rel_std": np.sqrt(np.maximum(np.diag(cov_sw), 0.0)).tolist(),
               "model_error": me_info | {
                   "nuisance": {"profile_amplitude_rel_std": self.profile_amplitude_rel_std,
                                "timing_std_s": self.timing_std_s,
                                "rel_std": np.sqrt(np.maximum(np.diag(cov_nu), 0.0)).tolist(),
                                "dlog_gain_per_log_amplitude": g_amp.tolist(),
                                "dlog_gain_per_s_timing": g_tau.tolist()}},
               "residual_rms_mps2": sigma,
               "white_noise_rel_std": np.sqrt(np.diag(np.linalg.pinv((J / sigma).T @ (J / sigma))))
               .tolist(), "jacobian_condition": float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf"),
               "compared_s": [m.ev.compared_s for m in models], "max_rel_std": self.max_rel_std,
               "polish": {"nfev": int(sol.nfev), "status": int(sol.status)}}
        return MagnetUpdate(
            names=space.names, nominal=tuple(map(float, space.nominal)), values=tuple(map(float, values)),
            std=std, identifiable=identifiable, static_current_a=float(i0),
            identifiability=ident, nrmse_nominal=nrmse(nominal_pred, meas),
            nrmse_updated=nrmse(r_opt + meas, meas),
            pareto=ParetoResult(space.from_theta(pareto.x), pareto.f, pareto.n_evaluations, pareto.n_iterations),
            grp_index=grp.index, n_model_evaluations=sum(m.n_evaluations for m in models),
            wall_time_s=time.perf_counter() - t_start, surrogate_score=surrogate_score, theta_cov=cov,
            uncertainty=unc)


# ------------------------------------------------------------------------------------- fallback

def irregularity_from_signals(time_s: np.ndarray, accel_mps2: np.ndarray, gap_m: np.ndarray,
                              position_m: np.ndarray, magnet_offsets_m: Sequence[float], nominal_gap_m: float,
                              detrend_order: int = 3, spacing_m: float | None = None,
                              modal=None, magnet_force_n: np.ndarray | None = None,
                              deflection_m: np.ndarray | None = None,
                              lowpass_hz: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """FALLBACK only (used when ``irregularity.twin_input.profile_for_twin`` fails; the pipeline says
    so in its log and provenance): simple inertial-reference reconstruction of r(x) from one pass.
    It leaves a true-gain NRMSE of ~0.06-0.1 (vs 0.03-0.06 for ``profile_for_twin``).

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
    covered = np.isfinite(prof).sum(axis=0)
    for _ in range(4):
        # mean over the magnets covering each point (NaN where none does, without numpy's
        # "Mean of empty slice" warning when the magnets' stretches do not overlap)
        mean = np.where(covered > 0, np.nansum(prof, axis=0) / np.maximum(covered, 1), np.nan)
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
