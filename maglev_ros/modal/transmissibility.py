"""Operational modal identification from transmissibility functions (the paper's method, 000
section 3): transmissibilities between test points, a rational-fraction polynomial (RFP) fit with
Forsythe orthogonal polynomials, a stabilization diagram, and poles -> frequency and damping.

The known weakness and how it is handled
----------------------------------------
A classical transmissibility ``T_ij = X_i / X_j`` under ONE loading condition converges, at every
system pole, to the ratio of mode-shape components ``phi_i / phi_j``: the poles cancel and T has no
peaks there, so its own poles are NOT the structure's (they are load-dependent zeros). Devriendt &
Guillaume (2007/2008) use several loading conditions: the difference of two transmissibilities
measured under different loads vanishes at the poles, so its inverse has the system poles as poles.
With a single ambient loading we use the PSD-transmissibility (PSDT) variant (Yan & Ren 2012,
Devriendt et al. 2009): ``T_ij^(k) = S_ik / S_jk`` built with different *reference outputs* k.
All ``T_ij^(k)`` also converge to ``phi_i / phi_j`` at each pole, whatever k and whatever the load,
so ``Delta_ij^(k1,k2) = T_ij^(k1) - T_ij^(k2)`` has zeros at the poles and
``1 / Delta_ij^(k1,k2)`` has the system poles as poles. Many such functions (all outputs i, a few
(j, k1, k2) triples) are fitted with ONE common denominator; the zeros of the individual Delta
functions differ between functions, so they do not survive the common-denominator fit and the
stabilization diagram.

Choices (the paper gives no equations)
--------------------------------------
* spectra are positive half spectra from output correlations (FFT, lags up to ``max_lag_s``) with
  an exponential window ``exp(-beta t)``; the window shifts every pole by exactly ``-beta``, which
  is corrected (sigma_true = sigma_fit - beta). Half spectra carry only the stable poles;
* the RFP fit is done band-wise (overlapping bands of ``band_width_hz``; each band keeps the poles
  of its middle half) in a normalized frequency ``x = (w - w_c) / w_h`` on [-1, 1] with complex
  coefficients (one root per mode, no mirrored roots); numerator and denominator bases are
  Forsythe orthogonal polynomials on the fit frequencies (Stieltjes three-term recurrence); the
  numerator coefficients are eliminated in closed form (orthogonal projections), leaving a small
  normal-equation system for the denominator with its highest coefficient fixed to 1; Levy's
  linearization is followed by two Sanathanan-Koerner re-weightings. Roots come from the comrade
  matrix of the recurrence (no conversion to the ill-conditioned power basis);
* a pole is stable when frequency / damping change less than 1 % / 10 % between orders (no MAC);
  physical poles are clusters over orders (same clustering as SSI-cov);
* mode shapes: first left singular vector of the half-spectrum matrix at the damped frequency
  (near a pole it is proportional to phi, i.e. it holds the ratios the PSDTs converge to, without
  depending on one reference channel that may sit at a node of the mode).
* ``source="psdt"`` (the paper's transmissibility route, with the Devriendt/Yan fix): each
  ``1/Delta`` function (one per test point) is fitted on its own and the poles of all test points
  are clustered (the paper averages over test points). It is exact on exact spectra (tested), but
  on noisy ambient records ``Delta`` is a difference of two nearly equal estimated ratios, so its
  inverse is noisy: in our simulations (120 s, 5 % noise) it finds the dominant modes within
  ~0.5 % but misses weakly observed ones.
* ``source="half-spectra"`` (default): one common-denominator fit of all positive half spectra
  per band, i.e. the same RFP/Forsythe machinery on functions that carry the poles directly.
  More robust on ambient data (all simulated modes within ~0.4 % / 0.35 pp), but still less
  accurate than :class:`maglev_ros.modal.ssi_cov.SSICov`, which the rest of the suite uses.

Hand-written: no maintained Python library implements PSDT / Forsythe-RFP OMA.
"""
from __future__ import annotations

import numpy as np
import scipy.fft as sfft
import scipy.linalg

from maglev_ros.errors import UserError
from maglev_ros.modal.ssi_cov import Mode, ModalResult, blas_threads, decimate
from maglev_ros.modal.stabilization import (
    PoleTable, StabilityCriteria, cluster_poles, mpc, mpd, real_mode_shape, stability_flags,
    sv_spectrum,
)


# --------------------------------------------------------------------------------------------
# Forsythe orthogonal polynomials and the RFP fit
# --------------------------------------------------------------------------------------------
def forsythe_basis(x: np.ndarray, order: int, weights: np.ndarray | None = None):
    """Orthonormal polynomials p_0..p_order on the real points ``x`` (Stieltjes recurrence
    ``x p_n = b_{n+1} p_{n+1} + a_n p_n + b_n p_{n-1}``, with one re-orthogonalization pass).

    Returns (P (len(x), order+1), a (order+1,), b (order+2,)).
    """
    w = np.ones_like(x) if weights is None else weights
    p = np.zeros((x.size, order + 1))
    a = np.zeros(order + 1)
    b = np.zeros(order + 2)
    p[:, 0] = 1.0 / np.sqrt(np.sum(w))
    prev = np.zeros_like(x)
    for n in range(order + 1):
        a[n] = np.sum(w * x * p[:, n] ** 2)
        q = x * p[:, n] - a[n] * p[:, n] - b[n] * prev
        # re-orthogonalize against all previous polynomials (keeps high orders orthogonal)
        q -= p[:, :n + 1] @ (p[:, :n + 1].T @ (w * q))
        b[n + 1] = np.sqrt(np.sum(w * q * q))
        if n < order:
            prev = p[:, n]
            p[:, n + 1] = q / b[n + 1]
    return p, a, b


def comrade_roots(d: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Roots of sum_n d_n p_n(x) (orthonormal basis with recurrence a, b), d[-1] != 0."""
    n = d.size - 1
    if n < 1:
        return np.zeros(0, complex)
    m = np.zeros((n, n), dtype=complex)
    m[np.arange(n), np.arange(n)] = a[:n]
    if n > 1:
        m[np.arange(1, n), np.arange(n - 1)] = b[1:n]
        m[np.arange(n - 1), np.arange(1, n)] = b[1:n]
    m[n - 1, :] -= b[n] * d[:n] / d[n]
    return np.linalg.eigvals(m)


def rfp_common_denominator(h: np.ndarray, p: np.ndarray, order: int, num_order: int | None = None,
                           sk_iterations: int = 2):
    """Least-squares common denominator of the functions ``h`` (K, n_functions):
    ``h_f(x) ~ N_f(x) / D(x)``, linearized residual ``(N_f - h_f D) / D_prev`` (Levy, then
    ``sk_iterations`` Sanathanan-Koerner re-weightings that remove most of Levy's bias); the
    numerator coefficients are eliminated (orthogonal projection). Returns d (order+1,),
    d[order] = 1."""
    nn = order if num_order is None else num_order
    theta = p[:, :order + 1]
    wts = np.ones(p.shape[0])
    d = None
    for it in range(sk_iterations + 1):
        if it == 0:
            q = p[:, :nn + 1]                                     # orthonormal already
        else:
            den = np.abs(theta @ d)
            wts = 1.0 / np.maximum(den, 1e-12 * den.max())
            wts /= np.sqrt(np.mean(wts ** 2))
            q, _ = np.linalg.qr(wts[:, None] * p[:, :nn + 1])
        mtx = np.zeros((order + 1, order + 1), dtype=complex)
        for f in range(h.shape[1]):
            x = (wts * h[:, f])[:, None] * theta
            proj = q.T @ x
            mtx += x.conj().T @ x - proj.conj().T @ proj
        d = np.ones(order + 1, dtype=complex)
        d[:order] = np.linalg.lstsq(mtx[:order, :order], -mtx[:order, order], rcond=None)[0]
    return d


def half_spectra(y: np.ndarray, refs: np.ndarray, fs_hz: float, max_lag: int, freqs_hz: np.ndarray,
                 beta: float) -> np.ndarray:
    """Positive half spectra S+_{i,k}(f) (len(freqs), l, len(refs)) from FFT correlations with
    an exponential lag window exp(-beta t) and half weight at lag 0."""
    n, l = y.shape
    nfft = sfft.next_fast_len(n + max_lag)
    fy = sfft.rfft(y, n=nfft, axis=0, workers=-1)
    lags = np.arange(max_lag)
    win = np.exp(-beta * lags / fs_hz) / (n - lags)
    win[0] *= 0.5
    out = np.empty((freqs_hz.size, l, refs.size), dtype=complex)
    ph = np.exp(-2j * np.pi * np.outer(freqs_hz, lags) / fs_hz)          # (F, L)
    for c, k in enumerate(refs):
        r = sfft.irfft(fy * fy[:, k:k + 1].conj(), n=nfft, axis=0, workers=-1)[:max_lag]
        out[:, :, c] = ph @ (r * win[:, None])
    return out


class TransmissibilityID:
    """PSD-transmissibility OMA with a Forsythe-polynomial RFP fit (see module docstring).

    ``freq_range_hz`` fit band, ``orders`` denominator orders (number of poles in the band),
    ``references``: list of (j, k1, k2) channel triples (indices or names; default: three triples
    from five least-redundant channels, QR column pivoting on the correlation matrix), ``max_lag_s`` correlation length,
    ``window_end`` value of the exponential window at the last lag, ``df_hz`` frequency spacing,
    ``decimate_to_hz`` optional decimation.
    """

    def __init__(self, freq_range_hz: tuple[float, float] = (5.0, 150.0), orders=range(2, 25, 2),
                 references=None, max_lag_s: float = 2.0, window_end: float = 0.01,
                 df_hz: float | None = None, decimate_to_hz: float | None = None,
                 criteria: StabilityCriteria | None = None, spectrum: bool = True,
                 source: str = "half-spectra", sk_iterations: int = 2,
                 band_width_hz: float | None = 40.0,
                 blas_threads: int | None = 1):
        self.freq_range_hz = (float(freq_range_hz[0]), float(freq_range_hz[1]))
        if not 0 <= self.freq_range_hz[0] < self.freq_range_hz[1]:
            raise UserError(f"freq_range_hz: expected 0 <= low < high, got {freq_range_hz!r}")
        self.orders = np.array(sorted({int(o) for o in orders}))
        self.references = references
        self.max_lag_s = float(max_lag_s)
        self.window_end = float(window_end)
        self.df_hz = df_hz
        self.decimate_to_hz = decimate_to_hz
        self.criteria = criteria or StabilityCriteria(min_mpc=0.0)
        self.spectrum = bool(spectrum)
        if source not in ("psdt", "half-spectra"):
            raise UserError(f"source: expected 'psdt' or 'half-spectra', got {source!r}")
        self.source = source
        self.sk_iterations = int(sk_iterations)
        self.band_width_hz = band_width_hz
        self.blas_threads = blas_threads

    def fit(self, data, fs_hz: float, channels=None) -> ModalResult:
        with blas_threads(self.blas_threads):
            return self._fit(data, fs_hz, channels)

    def _bands(self, f_lo, f_hi):
        """(fit_lo, fit_hi, core_lo, core_hi) per band: overlapping bands of ``band_width_hz``
        whose cores (middle halves; the outer edges at the range ends) tile the range."""
        bw = self.band_width_hz
        if bw is None or bw >= f_hi - f_lo:
            return [(f_lo, f_hi, f_lo, f_hi)]
        out = []
        step = bw / 2
        c = f_lo
        while c < f_hi:
            b_lo = max(f_lo, c - bw / 4)
            b_hi = min(f_hi, b_lo + bw)
            b_lo = max(f_lo, b_hi - bw)
            c_hi = min(f_hi, c + step)
            out.append((b_lo, b_hi, c, c_hi))
            c = c_hi
        return out

    def _triples(self, y, channels):
        l = y.shape[1]
        if l < 3:
            raise UserError(f"data: transmissibility needs >= 3 channels, got {l}")
        if self.references is not None:
            out = []
            for tr in self.references:
                idx = []
                for c in tr:
                    if isinstance(c, (int, np.integer)):
                        idx.append(int(c))
                    elif c in channels:
                        idx.append(channels.index(c))
                    else:
                        raise UserError(f"references: channel {c!r} not in {list(channels)}")
                if len(set(idx)) != 3 or not all(0 <= i < l for i in idx):
                    raise UserError(f"references: expected (j, k1, k2) of 3 distinct channels, got {tr!r}")
                out.append(tuple(idx))
            return out
        # references that see different modes: QR with column pivoting on the channel correlation
        # matrix picks a well-conditioned (least redundant) subset
        z = y / np.where(y.std(axis=0) > 0, y.std(axis=0), 1.0)
        corr = z.T @ z / z.shape[0]
        _, _, piv = scipy.linalg.qr(corr, pivoting=True)
        top = [int(i) for i in piv[:min(l, 5)]]
        trip = [(top[0], top[1], top[2])]
        if len(top) >= 4:
            trip.append((top[1], top[2], top[3]))
        if len(top) >= 5:
            trip.append((top[2], top[3], top[4]))
        return trip

    def _fit(self, data, fs_hz, channels):
        y = np.asarray(data, dtype=float)
        if y.ndim != 2:
            raise UserError(f"data: expected a 2-D array (n_samples, n_channels), got shape {y.shape}")
        if not np.all(np.isfinite(y)):
            raise UserError("data: expected finite samples, found NaN or inf")
        channels = tuple(str(c) for c in (channels or [f"ch{k}" for k in range(y.shape[1])]))
        if len(channels) != y.shape[1]:
            raise UserError(f"channels: expected {y.shape[1]} names, got {len(channels)}")
        y, fs = decimate(y, fs_hz, self.decimate_to_hz)
        y = y - y.mean(axis=0)
        f_lo, f_hi = self.freq_range_hz
        if f_hi >= fs / 2:
            raise UserError(f"freq_range_hz: upper limit {f_hi} Hz must be below Nyquist {fs / 2} Hz")
        max_lag = int(round(self.max_lag_s * fs))
        if y.shape[0] < 4 * max_lag:
            raise UserError(f"data: {y.shape[0]} samples, expected at least {4 * max_lag} for "
                            f"max_lag_s={self.max_lag_s}")
        beta = -np.log(self.window_end) / self.max_lag_s
        df = self.df_hz or 1.0 / (2 * self.max_lag_s)
        freqs = np.arange(f_lo, f_hi + 0.5 * df, df)
        triples = self._triples(y, channels)
        if self.source == "half-spectra":
            refs = np.array(sorted({k for t in triples for k in t}))
        else:
            refs = np.array(sorted({k for t in triples for k in t[1:]}))
        col = {int(k): c for c, k in enumerate(refs)}
        s = half_spectra(y, refs, fs, max_lag, freqs, beta)
        funcs, trans, groups = [], [], []
        for j, k1, k2 in triples:
            t1 = s[:, :, col[k1]] / s[:, j:j + 1, col[k1]]
            t2 = s[:, :, col[k2]] / s[:, j:j + 1, col[k2]]
            trans.append((j, t1, t2))
            if self.source == "psdt":
                for i in range(y.shape[1]):
                    if i in (j, k1, k2):
                        continue
                    inv = 1.0 / (t1[:, i] - t2[:, i])
                    funcs.append(inv / np.sqrt(np.mean(np.abs(inv) ** 2)))
        if self.source == "half-spectra":
            for c in range(refs.size):
                for i in range(y.shape[1]):
                    g = s[:, i, c]
                    funcs.append(g / np.sqrt(np.mean(np.abs(g) ** 2)))
            groups = [np.arange(len(funcs))]               # one common denominator
        else:
            groups = [np.array([f]) for f in range(len(funcs))]   # one fit per test point
        h_all = np.column_stack(funcs)
        n_max = int(self.orders[-1])
        rows_o, rows_f, rows_z, rows_g = [], [], [], []
        gid = 0
        for b_lo, b_hi, c_lo, c_hi in self._bands(f_lo, f_hi):
            sel = (freqs >= b_lo) & (freqs <= b_hi)
            if n_max >= sel.sum() // 2:
                raise UserError(f"orders: max order {n_max} too high for {int(sel.sum())} frequency "
                                f"lines in the band {b_lo:.1f}-{b_hi:.1f} Hz")
            wc, wh = 2 * np.pi * (b_lo + b_hi) / 2, 2 * np.pi * (b_hi - b_lo) / 2
            x = (2 * np.pi * freqs[sel] - wc) / wh
            p, a, b = forsythe_basis(x, n_max)
            for g in groups:
                for n in self.orders:
                    d = rfp_common_denominator(h_all[sel][:, g], p, int(n),
                                               sk_iterations=self.sk_iterations)
                    roots = comrade_roots(d, a, b)
                    w = wc + wh * roots                       # complex angular frequency
                    sigma = w.imag - beta                     # window correction
                    wd = w.real
                    keep = (wd > 2 * np.pi * c_lo) & (wd <= 2 * np.pi * c_hi)
                    lam_abs = np.hypot(wd[keep], sigma[keep])
                    rows_o.append(np.full(int(keep.sum()), n))
                    rows_f.append(lam_abs / (2 * np.pi))
                    rows_z.append(sigma[keep] / lam_abs)
                    rows_g.append(np.full(int(keep.sum()), gid))
                gid += 1
        n_fits_per_pole = len(groups)
        order = np.concatenate(rows_o) if rows_o else np.zeros(0, int)
        freq = np.concatenate(rows_f) if rows_f else np.zeros(0)
        zeta = np.concatenate(rows_z) if rows_z else np.zeros(0)
        group = np.concatenate(rows_g) if rows_g else np.zeros(0, int)
        ones = np.ones(freq.size)
        stable = np.zeros(freq.size, dtype=np.int8)
        for gi in range(gid):
            sel = group == gi
            stable[sel] = stability_flags(order[sel], freq[sel], zeta[sel], None, self.criteria)
        # clustering over (test point, order): a mode must be stable in a fraction of all fits
        pseudo_order = group * (int(self.orders[-1]) + 1) + order
        clusters, labels = cluster_poles(pseudo_order, freq, zeta, None, ones, stable,
                                         self.criteria, (f_lo, f_hi),
                                         n_orders=self.orders.size * n_fits_per_pole)
        table = PoleTable(order, freq, zeta, None, ones, stable, labels)
        modes, cshapes = [], []
        for k, cl in enumerate(clusters):
            fd = cl.frequency_hz * np.sqrt(max(1 - cl.damping_ratio ** 2, 0.0))
            q = int(np.argmin(np.abs(freqs - fd)))
            # shape: first left singular vector of the half-spectrum matrix S+(f_d) (l x refs);
            # near a pole S+ ~ phi gamma^T, the same ratios phi_i/phi_j the PSDTs converge to
            u, _, _ = np.linalg.svd(s[q], full_matrices=False)
            phi = u[:, 0]
            shape = real_mode_shape(phi)
            modes.append(Mode(id=f"M{k + 1}", frequency_hz=cl.frequency_hz,
                              damping_ratio=cl.damping_ratio,
                              mode_shape={c: float(v) for c, v in zip(channels, shape)},
                              mpc=mpc(phi), mpd=mpd(phi), std_frequency_hz=cl.std_frequency_hz,
                              std_damping_ratio=cl.std_damping_ratio))
            cshapes.append(phi)
        spec = sv_spectrum(y, fs) if self.spectrum else None
        method = "psd-transmissibility" if self.source == "psdt" else "half-spectra-rfp"
        return ModalResult(tuple(modes), table, spec, float(fs), channels, method, "cluster",
                           tuple(cshapes))
