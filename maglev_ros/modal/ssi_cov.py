"""Covariance-driven stochastic subspace identification (SSI-cov) of output-only vibration data.

Algorithm (Peeters & De Roeck 1999, with the fast multi-order step of Doehler & Mevel 2012):

1. optional anti-alias decimation (polyphase FIR, ``scipy.signal.resample_poly``) and demeaning;
2. output covariances ``R_k = 1/M sum_t y_{t+k} y_t[refs]^T`` for k = 0..2i with the SAME
   summation range for every lag (fixed-range sums, evaluated by segment-wise FFT cross-spectra
   accumulated in the frequency domain, see :func:`output_covariances`). The
   fixed range keeps the exact shift structure ``R_k = C A^(k-1) G`` also for transient
   (free-decay) data, so the same code identifies a vehicle pass' free decay;
3. block Hankel ``H[p, q] = R_{p+q+1+s}`` (i block rows, i block columns, reference columns,
   lag shift s, see below), ONE SVD at the maximum order, observability ``O = U_n S_n^(1/2)``;
4. all lower orders from one QR of the upper shifted observability matrix:
   ``O_up = Q R`` gives ``A_n = R[:n,:n]^-1 (Q^T O_down)[:n,:n]`` (least squares for every n
   at the cost of an n x n triangular solve);
5. poles ``lambda = fs ln(mu)``, shapes ``phi = C psi``; stabilization and automatic selection of
   physical poles by hierarchical clustering (:mod:`maglev_ros.modal.stabilization`).

Shift-invariance check (``lag_shift``, instrumental-variable principle): the modes selected from
the classic Hankel (lags 1..2i) are kept only if the same mode (frequency within 5 %, MAC above
``criteria.duplicate_mac``) is also selected from the Hankel of lags ``1+s .. 2i+s``. For a
structural mode ``R_{k+s} = C A^(k-1) (A^s G)``: the same poles, so a true mode passes. Output
components with a SHORT memory drop out of the shifted Hankel: sensor noise (lag 0 only) and,
above all, the direct feed-through of the forces into accelerations (the mass line
``phi phi^T p`` of every mode above its resonance), white only before the acquisition's
anti-alias filter and, after it, correlated over the filter's impulse-response length. Fitted
from lags 1.., that short-memory, mode-1-shaped covariance produced a stable, heavily damped
(4-9 %) spurious "mode" between the first two bending modes of simulated ambient records (issue 4:
30.5 Hz beside 23.5 and 92.2 Hz; gone when the feed-through is removed, or when both the force
band edge and the anti-alias filter are). Default ``lag_shift=None``: the lag beyond which the
normalized autocorrelation of the slowest-decaying common acquisition filter (8th-order
Butterworth, corner 0.4 x the identification rate) stays below 1 % (:func:`anti_alias_memory_lags`,
8 lags); structural modes in range have memories of tens to hundreds of lags. The reported
estimates stay those of the classic Hankel (identifying from the shifted lags alone removes the
artifact too but measurably increases the scatter of some modes). ``lag_shift=0``: no check.

The polish runs in :meth:`SSICov.fit` on stationary records (``uncertainty="blocks"``); free
decays (``uncertainty="cluster"``) and the streaming path (:meth:`SSICov.fit_covariances`, which
has no raw record) keep plain SSI-cov. With the polish the reported std is the inverse Fisher
information of the band likelihood (``ModalResult.uncertainty == "fisher"``).

Uncertainty (``uncertainty="blocks"``, default): the record is split into ``n_blocks`` equal
blocks; each block's covariance Hankel ``H_b`` is projected on the full-data right singular
subspace, ``O_b = H_b V_n S_n^(-1/2)`` (first-order equivalent to re-running the SVD, since the
change of the right subspace only changes the state basis to first order), and the modes are
re-estimated per block at the mode's representative order. The reported std is the sample std of
the block estimates divided by sqrt(n_blocks) (batch-means / Reynders et al. 2008 style). With
``uncertainty="cluster"`` (used for free decays, where blocks are not exchangeable) the std is the
spread of the stable poles within the mode's cluster across model orders, a cruder indicator.

Accuracy and the 0.2 % criterion (issue 4; bench/bench_modal_accuracy.py, tests/test_modal_accuracy.py).
The Cramer-Rao bound of a lightly damped mode driven by white noise and observed for T seconds is
``std(f)/f = std(zeta) = sqrt(zeta / (2 pi f T))`` (Whittle information of the Lorentzian peak;
the multichannel bound of the exact simulated 15-channel structure with 5 % noise agrees within
5 %, and an oracle AR(2) maximum-likelihood fit of an exact single mode reaches it). At 120 s the
bound is 0.093 % for the 23.49 Hz, 1.5 %-damped mode (0.06-0.07 % for the others), so 0.2 % is
2.15 sigma there: an efficient unbiased estimator misses 0.2 % on that mode in 3.2 % of records
and on at least one of the six modes below 150 Hz in 3.8 % (nominal structure; 9 % for a
2.5 %-damped first mode). "< 0.2 % for every mode on every record" is therefore not reachable at
120 s by any estimator. Since std ~ 1/sqrt(T): 0.2 % = 2.6 sigma on the first mode (about 1 % of
records failing) needs T ~ 175 s for an efficient estimator and ~250 s for ours (1.2 x the bound).
Measured (80 records, nominal structure, 120 s), frequency std / bound per mode 23.5 .. 132 Hz:
plain SSI-cov (``polish=None``) 1.19-1.27, 1.06-1.11, 1.29-1.70, 1.30-1.39, 1.77-2.07, 1.72-2.15 (it
discards up to 3/4 of the information on the upper modes); with the default Whittle
maximum-likelihood polish of each selected pole (:mod:`maglev_ros.modal.polish`) 1.18-1.21, 1.06-1.17,
1.21-1.43, 1.14-1.22, 1.21-1.26, 1.24-1.39, i.e. 14-35 % lower std on 43.8-132 Hz, unchanged on
the two lowest modes; damping std 0.8-1.6 x its bound. The remaining ~1.2 x comes from what an
estimator must not assume: the polish fits a band of +-20 half-power half-widths (capped at
+-30 % of f) with a free spectral tilt, because the excitation colour and sensor dynamics are
unknown (without the tilt it reached 0.9-1.2 x but was biased by up to 0.43 % on the upper
modes by the mismatch of the assumed peak shape across the band; with the tilt and a wider band,
+-40 half-widths / 50 %, it was biased by up to 0.18 % on coloured excitation). Records whose
worst mode misses 0.2 %: 10-15 % with the polish, 12.5-22.5 % without (40-record runs; dominated
by the 23.5 Hz mode at 1.2 x its bound, where 0.2 % = 1.8 sigma). Residual bias: +0.03..0.06 % on the 43.8 Hz partner of the close pair (imperfect
spatial separation of correlated modal responses; SSI-cov alone +0.00..0.04 %), <= 0.03 %
elsewhere. A randomized structure (variant 4, 30 records) gives the same picture: std / bound
1.25, 0.83, 1.17, 1.11, 1.24, 1.29 with the polish vs 1.28, 0.88, 1.13, 1.46, 1.83, 1.92 without.
Alternatives measured on the same 30 records and not adopted: 60 or 80 block rows (longer lags)
raise the std (43.8 Hz: 0.23 / 0.16 % vs 0.15 %; 79.7 Hz: 0.11 / 0.12 % vs 0.08 %); the mean
over the orders of the stable cluster equals the median used (within 3 %); all channels are
already references.

Hand-written instead of using koma-python / pyOMA2: those build the Hankel matrix from the full
lagged data matrices and redo an SVD/pseudo-inverse per order, which is far slower (see
bench/bench_modal.py), and they pull in GUI/plot stacks.
"""
from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.linalg import solve_triangular
from scipy.signal import butter, resample_poly, sosfilt

from maglev_ros.errors import UserError
from maglev_ros.modal.stabilization import (
    PoleTable, Spectrum, StabilityCriteria, cluster_poles, mac, mpc, mpd, poles_from_eigs,
    real_mode_shape, stability_flags, sv_spectrum,
)

SCHEMA = "maglev-modes/1"


# --------------------------------------------------------------------------------------------
# results
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Mode:
    """One identified mode. ``mode_shape`` is real, normalized to max |value| = 1."""
    id: str
    frequency_hz: float
    damping_ratio: float
    mode_shape: dict
    mpc: float
    mpd: float
    std_frequency_hz: float
    std_damping_ratio: float

    def to_dict(self) -> dict:
        return {
            "id": self.id,
            "frequency_hz": float(self.frequency_hz),
            "damping_ratio": float(self.damping_ratio),
            "mode_shape": {str(k): float(v) for k, v in self.mode_shape.items()},
            "mpc": float(self.mpc),
            "mpd": float(self.mpd),
            "std_frequency_hz": _json_float(self.std_frequency_hz),
            "std_damping_ratio": _json_float(self.std_damping_ratio),
        }

    def shape_vector(self, channels) -> np.ndarray:
        return np.array([self.mode_shape[c] for c in channels], dtype=float)


def _json_float(x: float):
    return None if x is None or not np.isfinite(x) else float(x)


@dataclass(frozen=True)
class ModalResult:
    """Identified modes plus the stabilization diagram (poles per order) and the spectrum."""
    modes: tuple
    stabilization: PoleTable | None
    spectrum: Spectrum | None
    fs_hz: float = 0.0                      # sampling rate the identification ran at
    channels: tuple = ()
    method: str = "ssi-cov"
    uncertainty: str = "blocks"
    complex_shapes: tuple = field(default=(), repr=False)   # per mode, complex, for MAC

    def to_dict(self, diagram: bool = False) -> dict:
        out = {"schema": SCHEMA, "modes": [m.to_dict() for m in self.modes]}
        if diagram:
            out["method"] = self.method
            out["fs_hz"] = float(self.fs_hz)
            out["uncertainty"] = self.uncertainty
            if self.stabilization is not None:
                out["stabilization"] = self.stabilization.to_dict()
            if self.spectrum is not None:
                out["spectrum"] = self.spectrum.to_dict()
        return out

    def frequencies_hz(self) -> np.ndarray:
        return np.array([m.frequency_hz for m in self.modes], dtype=float)


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------
_CONTROLLER = []


def blas_threads(n: int | None):
    """Context limiting BLAS threads (threadpoolctl when installed). The matrices here are small
    (<= ~1000): multi-threaded OpenBLAS gains little and, on a loaded 2-core machine shared with
    other nodes, its spin-waiting makes SVD/QR 10x slower, so estimators default to 1 thread."""
    if n is None:
        return contextlib.nullcontext()
    if not _CONTROLLER:
        try:
            from threadpoolctl import ThreadpoolController
            _CONTROLLER.append(ThreadpoolController())   # scans the loaded libraries once
        except Exception:  # pragma: no cover - optional dependency
            _CONTROLLER.append(None)
    ctl = _CONTROLLER[0]
    if ctl is None:  # pragma: no cover
        return contextlib.nullcontext()
    return ctl.limit(limits=int(n), user_api="blas")


@functools.lru_cache(maxsize=None)
def anti_alias_memory_lags(order: int = 8, cutoff_frac: float = 0.4, threshold: float = 0.01) -> int:
    """Number of lags (at the recorded rate) after which the normalized autocorrelation of the
    impulse response of an analog-like Butterworth low-pass (``order``, corner ``cutoff_frac`` x
    rate; simulated at 16 x the rate) stays below ``threshold``: the memory of anti-alias-filtered
    white inputs."""
    over = 16
    sos = butter(order, cutoff_frac, fs=float(over), output="sos")
    imp = np.zeros(512 * over)
    imp[0] = 1.0
    h = sosfilt(sos, imp)
    r = np.correlate(h, h, "full")[h.size - 1:][::over]
    r = r / r[0]
    return int(np.max(np.flatnonzero(np.abs(r) > threshold)) + 1)


def decimation_factor(fs_hz: float, target_hz: float | None) -> int:
    """Largest integer factor that keeps the rate >= ``target_hz`` (1 = no decimation)."""
    if target_hz is None or target_hz <= 0 or target_hz >= fs_hz:
        return 1
    return max(1, int(np.floor(fs_hz / target_hz + 1e-9)))


def decimate(data: np.ndarray, fs_hz: float, target_hz: float | None) -> tuple[np.ndarray, float]:
    """Anti-aliased integer decimation (polyphase FIR); returns (data, new_fs_hz)."""
    q = decimation_factor(fs_hz, target_hz)
    if q == 1:
        return np.asarray(data, dtype=float), float(fs_hz)
    return resample_poly(np.asarray(data, dtype=float), 1, q, axis=0), float(fs_hz) / q


def output_covariances(y: np.ndarray, max_lag: int, refs: np.ndarray | None = None,
                       n_blocks: int = 1, seg_len: int = 2048) -> np.ndarray:
    """Fixed-range output covariances per block: array (n_blocks, max_lag+1, l, r).

    ``R_b[k] = 1/M sum_{t in block b, t < start_b + M} y_{t+k} y_t[refs]^T``, M = block - max_lag.
    Evaluated by FFT over segments: for each segment of L "early" samples, the cross-spectrum of
    the segment extended by ``max_lag`` "late" samples with the zero-padded early part (FFT size
    >= L + max_lag, so no circular wrap for lags 0..max_lag) is accumulated in the frequency
    domain; one inverse FFT per block at the end. Exact (to rounding) fixed-range sums at
    O(N l r) cost instead of O(N l r max_lag).
    """
    import scipy.fft as sfft
    y = np.ascontiguousarray(y, dtype=float)
    n, l = y.shape
    refs = np.arange(l) if refs is None else np.asarray(refs)
    r = refs.size
    edges = np.linspace(0, n, n_blocks + 1).astype(int)
    out = np.empty((n_blocks, max_lag + 1, l, r))
    seg = int(max(min(seg_len, n), 1))
    nfft = sfft.next_fast_len(seg + max_lag, real=True)
    nf = nfft // 2 + 1
    for b in range(n_blocks):
        s0, s1 = edges[b], edges[b + 1]
        m = s1 - s0 - max_lag
        if m <= 0:
            raise UserError(f"data: block of {s1 - s0} samples is shorter than {max_lag} lags; "
                            f"expected a longer record or fewer block_rows/n_blocks")
        acc = np.zeros((nf, l, r), dtype=complex)
        for c0 in range(s0, s0 + m, seg):
            c1 = min(c0 + seg, s0 + m)
            late = sfft.rfft(y[c0:c1 + max_lag], n=nfft, axis=0)
            early = sfft.rfft(y[c0:c1][:, refs], n=nfft, axis=0)
            acc += late[:, :, None] * early.conj()[:, None, :]
        corr = sfft.irfft(acc, n=nfft, axis=0)[:max_lag + 1]
        out[b] = corr / m
    return out


def block_hankel(cov: np.ndarray, block_rows: int) -> np.ndarray:
    """H[p, q] = R_{p+q+1}, p, q = 0..i-1, from covariances (2i+1, l, r) -> (l i, r i)."""
    i = block_rows
    _, l, r = cov.shape
    idx = np.arange(i)[:, None] + np.arange(i)[None, :] + 1          # (i, i) lag index
    return cov[idx].transpose(0, 2, 1, 3).reshape(l * i, r * i)


def top_svd(h: np.ndarray, k: int, v0: np.ndarray | None = None, n_iter: int = 1):
    """Leading k singular triplets of h: exact (LAPACK) or, with a warm start ``v0``, block
    subspace iteration started from the previous right singular vectors (streaming use)."""
    if v0 is None:
        u, s, vt = np.linalg.svd(h, full_matrices=False)
        return u[:, :k], s[:k], vt[:k].T
    p = min(h.shape[1], k + 10)
    v = v0[:, :p]
    if v.shape[1] < p:
        rng = np.random.default_rng(0)
        v = np.column_stack([v, rng.standard_normal((h.shape[1], p - v.shape[1]))])
    for _ in range(n_iter):
        q, _ = np.linalg.qr(h @ v)
        v, _ = np.linalg.qr(h.T @ q)
    q, _ = np.linalg.qr(h @ v)
    ub, s, vt = np.linalg.svd(q.T @ h, full_matrices=False)
    return (q @ ub)[:, :k], s[:k], vt[:k].T


def _observability_qr(o: np.ndarray, l: int):
    q, r = np.linalg.qr(o[:-l])
    return r, q.T @ o[l:]


def _a_matrix(r: np.ndarray, t: np.ndarray, n: int) -> np.ndarray:
    return solve_triangular(r[:n, :n], t[:n, :n], check_finite=False)


# --------------------------------------------------------------------------------------------
# estimator
# --------------------------------------------------------------------------------------------
class SSICov:
    """Covariance-driven SSI with automatic stabilization-diagram interpretation.

    Parameters: ``block_rows`` i (max lag 2i; pick i so that i/fs covers about one period of the
    lowest mode or more), ``orders`` model orders (even numbers; max order <= l i),
    ``decimate_to_hz`` (integer decimation to at least this rate), ``freq_range_hz`` (modes kept;
    default 0..0.45 fs), ``ref_channels`` (column indices or names used as references; default
    all), ``criteria`` (:class:`StabilityCriteria`), ``uncertainty`` ("blocks" | "cluster"),
    ``n_blocks``, ``spectrum`` (compute the singular-value spectrum for the diagram),
    ``blas_threads`` (BLAS threads during fit; None = leave the process setting alone),
    ``lag_shift`` (lag shift of the shift-invariance check of the selected modes;
    None = :func:`anti_alias_memory_lags`, 0 = no check; see the module docstring),
    ``polish`` ("whittle": maximum-likelihood refinement of each selected pole on the record's
    periodogram in ``fit``, stationary records with ``uncertainty="blocks"`` only; None: plain
    SSI-cov; see the module docstring).
    """

    def __init__(self, block_rows: int = 40, orders=range(2, 81, 2), decimate_to_hz: float | None = None,
                 freq_range_hz: tuple[float, float] | None = None, ref_channels=None,
                 criteria: StabilityCriteria | None = None, uncertainty: str = "blocks",
                 n_blocks: int = 10, spectrum: bool = True, nperseg: int = 1024,
                 blas_threads: int | None = 1, lag_shift: int | None = None,
                 polish: str | None = "whittle"):
        if int(block_rows) < 2:
            raise UserError(f"block_rows: expected an integer >= 2, got {block_rows!r}")
        self.block_rows = int(block_rows)
        self.orders = np.array(sorted({int(o) for o in orders}))
        if self.orders.size == 0 or self.orders[0] < 1:
            raise UserError(f"orders: expected positive model orders, got {list(orders)!r}")
        self.decimate_to_hz = decimate_to_hz
        self.freq_range_hz = freq_range_hz
        self.ref_channels = ref_channels
        self.criteria = criteria or StabilityCriteria()
        if uncertainty not in ("blocks", "cluster"):
            raise UserError(f"uncertainty: expected 'blocks' or 'cluster', got {uncertainty!r}")
        self.uncertainty = uncertainty
        self.n_blocks = int(n_blocks)
        self.spectrum = bool(spectrum)
        self.nperseg = int(nperseg)
        self.blas_threads = blas_threads
        if lag_shift is None:
            lag_shift = anti_alias_memory_lags()
        if not (isinstance(lag_shift, (int, np.integer)) and lag_shift >= 0):
            raise UserError(f"lag_shift: expected an integer >= 0, got {lag_shift!r}")
        self.lag_shift = int(lag_shift)
        if polish not in ("whittle", None):
            raise UserError(f"polish: expected 'whittle' or None, got {polish!r}")
        self.polish = polish

    @property
    def max_lag(self) -> int:
        """Highest covariance lag used: 2 block_rows + lag_shift (the shifted check Hankel)."""
        return 2 * self.block_rows + self.lag_shift

    # ---- public --------------------------------------------------------------------------
    def fit(self, data, fs_hz: float, channels=None) -> ModalResult:
        """Identify modes from ``data`` (n_samples, n_channels) sampled at ``fs_hz``."""
        with blas_threads(self.blas_threads):
            return self._fit(data, fs_hz, channels)

    def _fit(self, data, fs_hz, channels):
        y, fs, channels = self._prepare(data, fs_hz, channels)
        refs = self._ref_indices(channels)
        nb = self.n_blocks if self.uncertainty == "blocks" else 1
        covs = output_covariances(y, self.max_lag, refs, n_blocks=max(nb, 1))
        cov = covs.mean(axis=0)
        spec = sv_spectrum(y, fs, nperseg=min(self.nperseg, y.shape[0])) if self.spectrum else None
        res, _ = self.fit_covariances(cov, fs, channels, block_covs=covs if nb > 1 else None,
                                      spectrum=spec)
        if self.polish == "whittle" and res.uncertainty == "blocks" and res.modes:
            res = self._polish(y, fs, res)
        return res

    def _polish(self, y, fs, res):
        """Whittle maximum-likelihood refinement of frequency and damping (stationary records,
        :mod:`maglev_ros.modal.polish`); std from its Fisher information. Shapes unchanged."""
        from maglev_ros.modal.polish import WhittlePolish
        pol = WhittlePolish().fit(y, fs, [m.frequency_hz for m in res.modes],
                                  [m.damping_ratio for m in res.modes], np.array(res.complex_shapes),
                                  [m.std_frequency_hz for m in res.modes])
        return self.apply_polish(res, pol)

    @staticmethod
    def apply_polish(res, pol):
        """``res`` with the polished poles ``pol`` (one :class:`PolishedPole` per mode) in place."""
        modes = []
        for m, p in zip(res.modes, pol):
            if p.ok:
                m = replace(m, frequency_hz=float(p.frequency_hz), damping_ratio=float(p.damping_ratio),
                            std_frequency_hz=float(p.std_frequency_hz),
                            std_damping_ratio=float(p.std_damping_ratio))
            modes.append(m)
        n_ok = sum(p.ok for p in pol)
        return replace(res, modes=tuple(modes), method="ssi-cov+whittle" if n_ok else res.method,
                       uncertainty="fisher" if n_ok == len(pol) else ("blocks+fisher" if n_ok else "blocks"))

    def fit_covariances(self, cov: np.ndarray, fs_hz: float, channels, block_covs=None,
                        spectrum: Spectrum | None = None, v0: np.ndarray | None = None,
                        uncertainty: str | None = None):
        """Identify from precomputed covariances (lags 0..max_lag, l, r); returns (ModalResult, V) where V
        are the right singular vectors (warm start for the next call in streaming use)."""
        with blas_threads(self.blas_threads):
            return self._fit_covariances(cov, fs_hz, channels, block_covs, spectrum, v0, uncertainty)

    def _fit_covariances(self, cov, fs_hz, channels, block_covs, spectrum, v0, uncertainty):
        i = self.block_rows
        if cov.shape[0] < self.max_lag + 1:
            raise UserError(f"covariances: expected {self.max_lag + 1} lags (0..2 block_rows + "
                            f"lag_shift), got {cov.shape[0]}")
        l = cov.shape[1]
        channels = tuple(channels)
        fr = self.freq_range_hz or (0.0, 0.45 * fs_hz)
        poles = self._poles(cov[:2 * i + 1], fs_hz, v0, fr)
        if poles is None:
            table = PoleTable(np.zeros(0, int), np.zeros(0), np.zeros(0), np.zeros((0, l), complex),
                              np.zeros(0), np.zeros(0, np.int8), np.zeros(0, int))
            return ModalResult((), table, spectrum, fs_hz, channels, "ssi-cov",
                               uncertainty or self.uncertainty), None
        order, freq, zeta, shapes, mpcs, stable, clusters, labels, s, v = poles
        if self.lag_shift > 0 and clusters:
            k0 = self.lag_shift
            # same right (controllability) subspace as the classic Hankel: warm start from it
            check = self._poles(cov[k0:k0 + 2 * i + 1], fs_hz, v, fr)
            clusters = self._shift_invariant(clusters, shapes, check)
            labels = np.full(freq.size, -1, dtype=int)
            for k, c in enumerate(clusters):
                labels[c.members] = k
        table = PoleTable(order, freq, zeta, shapes, mpcs, stable, labels)
        unc = uncertainty or self.uncertainty
        stds = None
        if unc == "blocks" and block_covs is not None and block_covs.shape[0] >= 3 and clusters:
            stds = self._block_uncertainty(block_covs, v, s, l, fs_hz, clusters, table)
        else:
            unc = "cluster"
        modes, cshapes = [], []
        for k, cl in enumerate(clusters):
            phi = shapes[cl.representative]
            shape = real_mode_shape(phi)
            sf, sz = (cl.std_frequency_hz, cl.std_damping_ratio) if stds is None else stds[k]
            modes.append(Mode(id=f"M{k + 1}", frequency_hz=cl.frequency_hz,
                              damping_ratio=cl.damping_ratio,
                              mode_shape={ch: float(x) for ch, x in zip(channels, shape)},
                              mpc=float(mpcs[cl.representative]), mpd=mpd(phi),
                              std_frequency_hz=float(sf), std_damping_ratio=float(sz)))
            cshapes.append(phi)
        return ModalResult(tuple(modes), table, spectrum, float(fs_hz), channels, "ssi-cov", unc,
                           tuple(cshapes)), v

    # ---- internals -----------------------------------------------------------------------
    def _poles(self, cov, fs_hz, v0, fr):
        """Multi-order poles and clusters from the Hankel of covariances (2i+1, l, r) (lags
        0..2i; lag 0 unused); None when no oscillatory pole is found."""
        i = self.block_rows
        l = cov.shape[1]
        h = block_hankel(cov, i)
        n_max = int(self.orders[-1])
        if n_max > min(h.shape):
            raise UserError(f"orders: max order {n_max} exceeds the Hankel rank bound {min(h.shape)}"
                            f" (block_rows x channels); expected a lower order or more block_rows")
        u, s, v = top_svd(h, n_max, v0)
        sq = np.sqrt(np.maximum(s, 1e-300))
        o = u * sq
        rq, tq = _observability_qr(o, l)
        c = o[:l]
        rows_o, rows_f, rows_z, rows_s = [], [], [], []
        for n in self.orders:
            a = _a_matrix(rq, tq, n)
            mu, psi = np.linalg.eig(a)
            keep = mu.imag > 1e-10
            if not np.any(keep):
                continue
            _, f, z = poles_from_eigs(mu[keep], fs_hz)
            phi = c[:, :n] @ psi[:, keep]
            rows_o.append(np.full(f.size, n))
            rows_f.append(f)
            rows_z.append(z)
            rows_s.append(phi.T)
        if not rows_o:
            return None
        order = np.concatenate(rows_o)
        freq = np.concatenate(rows_f)
        zeta = np.concatenate(rows_z)
        shapes = np.concatenate(rows_s, axis=0)
        mpcs = np.array([mpc(p) for p in shapes])
        stable = stability_flags(order, freq, zeta, shapes, self.criteria)
        clusters, labels = cluster_poles(order, freq, zeta, shapes, mpcs, stable, self.criteria,
                                         fr, n_orders=self.orders.size)
        return order, freq, zeta, shapes, mpcs, stable, clusters, labels, s, v

    def _shift_invariant(self, clusters, shapes, check):
        """Keep the clusters that are also selected from the lag-shifted Hankel: same frequency
        within 5 % (the block matching tolerance) and MAC above ``criteria.duplicate_mac``."""
        if check is None:
            return []
        c_shapes, c_clusters = check[3], check[6]
        if not c_clusters:
            return []
        cf = np.array([c.frequency_hz for c in c_clusters])
        cs = np.array([c_shapes[c.representative] for c in c_clusters]).T
        keep = []
        for cl in clusters:
            m = mac(shapes[cl.representative][:, None], cs)[0]
            ok = (np.abs(cf - cl.frequency_hz) / cl.frequency_hz < 0.05) & (m > self.criteria.duplicate_mac)
            if np.any(ok):
                keep.append(cl)
        return keep

    def _block_uncertainty(self, block_covs, v, s, l, fs_hz, clusters, table):
        i = self.block_rows
        inv_sq = 1.0 / np.sqrt(np.maximum(s, 1e-300))
        nb = block_covs.shape[0]
        est_f = np.full((len(clusters), nb), np.nan)
        est_z = np.full((len(clusters), nb), np.nan)
        # one model order for all modes (the highest representative order: every selected mode
        # is present there), one eigen-decomposition per block
        n = int(max(table.order[cl.representative] for cl in clusters))
        for b in range(nb):
            hb = block_hankel(block_covs[b][:2 * i + 1], i)
            ob = (hb[:, :] @ v[:, :n]) * inv_sq[:n]
            q, r = np.linalg.qr(ob[:-l])
            a = solve_triangular(r, q.T @ ob[l:], check_finite=False)
            mu, psi = np.linalg.eig(a)
            keep = mu.imag > 1e-10
            _, f, z = poles_from_eigs(mu[keep], fs_hz)
            ph = ob[:l] @ psi[:, keep]
            if f.size == 0:
                continue
            for k, cl in enumerate(clusters):
                ref = table.shapes[cl.representative]
                d = np.abs(f - cl.frequency_hz) / cl.frequency_hz + (1 - mac(ref[:, None], ph)[0])
                j = int(np.argmin(d))
                if abs(f[j] - cl.frequency_hz) / cl.frequency_hz < 0.05:
                    est_f[k, b], est_z[k, b] = f[j], z[j]
        out = []
        for k, cl in enumerate(clusters):
            ok = np.isfinite(est_f[k])
            if ok.sum() >= 3:
                m = ok.sum()
                out.append((float(np.std(est_f[k, ok], ddof=1) / np.sqrt(m)),
                            float(np.std(est_z[k, ok], ddof=1) / np.sqrt(m))))
            else:
                out.append((cl.std_frequency_hz, cl.std_damping_ratio))
        return out

    def _prepare(self, data, fs_hz, channels):
        y = np.asarray(data, dtype=float)
        if y.ndim != 2:
            raise UserError(f"data: expected a 2-D array (n_samples, n_channels), got shape {y.shape}")
        if not np.isfinite(fs_hz) or fs_hz <= 0:
            raise UserError(f"fs_hz: expected a positive sampling rate, got {fs_hz!r}")
        if not np.all(np.isfinite(y)):
            raise UserError("data: expected finite samples, found NaN or inf")
        if channels is None:
            channels = tuple(f"ch{k}" for k in range(y.shape[1]))
        channels = tuple(str(c) for c in channels)
        if len(channels) != y.shape[1]:
            raise UserError(f"channels: expected {y.shape[1]} names, got {len(channels)}")
        y, fs = decimate(y, fs_hz, self.decimate_to_hz)
        y = y - y.mean(axis=0)
        need = (4 * self.block_rows + self.lag_shift) * max(self.n_blocks if self.uncertainty == "blocks" else 1, 1)
        if y.shape[0] < need:
            raise UserError(f"data: {y.shape[0]} samples after decimation, expected at least {need}"
                            f" for block_rows={self.block_rows}")
        return y, fs, channels

    def _ref_indices(self, channels):
        if self.ref_channels is None:
            return np.arange(len(channels))
        idx = []
        for r in self.ref_channels:
            if isinstance(r, (int, np.integer)):
                if not 0 <= r < len(channels):
                    raise UserError(f"ref_channels: index {r} outside 0..{len(channels) - 1}")
                idx.append(int(r))
            else:
                if r not in channels:
                    raise UserError(f"ref_channels: channel {r!r} not in {list(channels)}")
                idx.append(channels.index(r))
        return np.array(idx)
